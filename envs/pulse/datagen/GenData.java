// twinfalsify: writes Pulse's engine data files (config/, ecg/, environments/, nutrition/, patients/,
// substances/ and substances/compounds/) into the working directory from Pulse's data/Data.xlsx,
// with Pulse's own com.kitware.pulse.dataset.DataSetReader. Unlike DataSetReader.main it does not
// initialise the native PulseJNI bridge (not built); the POI classes and UnitConverter it needs are
// the stand-ins next to this file. Usage: java GenData <pulse-src>/data/Data.xlsx
public class GenData {
  public static void main(String[] args) {
    if (args.length != 1) {
      System.err.println("usage: java GenData <pulse-src>/data/Data.xlsx");
      System.exit(2);
    }
    com.kitware.pulse.dataset.DataSetReader.loadData(args[0]);
  }
}
