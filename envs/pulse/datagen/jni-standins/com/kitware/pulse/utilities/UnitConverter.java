// twinfalsify stand-in for Pulse's UnitConverter, whose methods call the native PulseJNI library
// (not built by build.sh). Used only by envs/pulse/datagen/GenData.java to write Pulse's data files:
// unit compatibility checks accept any unit (the spreadsheet's units are Pulse's own) and an actual
// conversion between two different units fails loudly (data generation requests none).
package com.kitware.pulse.utilities;

public class UnitConverter {
  public static double convert(double value, String fromUnit, String toUnit) {
    if (Double.isNaN(value) || fromUnit.equals(toUnit) || fromUnit.isEmpty() || toUnit.isEmpty())
      return value;
    throw new UnsupportedOperationException("UnitConverter stand-in: no conversion " + fromUnit + " -> " + toUnit);
  }

  public static double[] convert(double[] data, String fromUnit, String toUnit) {
    double[] out = new double[data.length];
    for (int i = 0; i < data.length; i++) out[i] = convert(data[i], fromUnit, toUnit);
    return out;
  }

  public static boolean isCompatibleWithUnit(String unitTemplate, String unit) { return unitTemplate != null; }

  public static boolean isCompatibleWithUnitList(String[] unitTemplates, String unit) { return unitTemplates != null; }

  public static boolean isOfQuantityType(String templateUnit, String unit) { return templateUnit != null; }

  public static boolean isOfQuantityTypes(String[] templateUnits, String unit) {
    return templateUnits != null && templateUnits.length > 0 && unit != null;
  }
}
