// twinfalsify stand-in for the Apache POI API used by Pulse's DataSetReader (see ../../xssf/usermodel/XSSFSheet.java).
package org.apache.poi.ss.usermodel;

public enum CellType { _NONE, NUMERIC, STRING, FORMULA, BLANK, BOOLEAN, ERROR }
