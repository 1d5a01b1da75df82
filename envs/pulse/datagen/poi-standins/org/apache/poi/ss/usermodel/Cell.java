// twinfalsify stand-in for the Apache POI API used by Pulse's DataSetReader.
package org.apache.poi.ss.usermodel;

public interface Cell {
  CellType getCellType();
  /** "" for a blank cell; IllegalStateException for a cell (or cached formula result) that is not text. */
  String getStringCellValue();
  /** 0 for a blank cell; IllegalStateException for a cell (or cached formula result) that is not a number. */
  double getNumericCellValue();
}
