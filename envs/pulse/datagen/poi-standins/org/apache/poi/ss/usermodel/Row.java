// twinfalsify stand-in for the Apache POI API used by Pulse's DataSetReader.
package org.apache.poi.ss.usermodel;

public interface Row {
  /** Number of cells present in the file for this row (POI semantics: every c element). */
  int getPhysicalNumberOfCells();
  /** Cell at 0-based column index, or null when the file has none there. */
  Cell getCell(int column);
}
