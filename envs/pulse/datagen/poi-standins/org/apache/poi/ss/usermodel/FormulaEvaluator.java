// twinfalsify stand-in for the Apache POI API used by Pulse's DataSetReader.
package org.apache.poi.ss.usermodel;

public interface FormulaEvaluator {
  /** Type of the formula's result (here: the result cached in the file); _NONE if not a formula cell. */
  CellType evaluateFormulaCell(Cell cell);
}
