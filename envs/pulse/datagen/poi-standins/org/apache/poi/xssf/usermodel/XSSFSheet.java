// twinfalsify stand-in for the part of Apache POI's XSSFSheet that Pulse's DataSetReader uses,
// with POI's semantics: physical rows/cells = elements present in the file, 0-based indices,
// cell type FORMULA when the cell has an f element, else from its t attribute.
package org.apache.poi.xssf.usermodel;

import java.util.ArrayList;
import java.util.List;
import java.util.TreeMap;
import org.apache.poi.ss.usermodel.Cell;
import org.apache.poi.ss.usermodel.CellType;
import org.apache.poi.ss.usermodel.Row;
import org.w3c.dom.Document;
import org.w3c.dom.Element;

public class XSSFSheet {
  private final TreeMap<Integer, XRow> rows = new TreeMap<>();

  XSSFSheet(XSSFWorkbook wb, Document doc) {
    int r = -1;
    for (Element re : XSSFWorkbook.elements(doc.getDocumentElement(), "row")) {
      r = re.hasAttribute("r") ? Integer.parseInt(re.getAttribute("r")) - 1 : r + 1;
      XRow row = new XRow();
      int c = -1;
      for (Element ce : XSSFWorkbook.elements(re, "c")) {
        c = ce.hasAttribute("r") ? column(ce.getAttribute("r")) : c + 1;
        row.cells.put(c, new XCell(wb, ce));
      }
      rows.put(r, row);
    }
  }

  public int getPhysicalNumberOfRows() { return rows.size(); }

  public Row getRow(int r) { return rows.get(r); }

  private static int column(String ref) { // "AB12" -> 27
    int c = 0;
    for (char ch : ref.toCharArray()) {
      if (!Character.isLetter(ch)) break;
      c = c * 26 + (Character.toUpperCase(ch) - 'A' + 1);
    }
    return c - 1;
  }

  static class XRow implements Row {
    final TreeMap<Integer, XCell> cells = new TreeMap<>();
    @Override public int getPhysicalNumberOfCells() { return cells.size(); }
    @Override public Cell getCell(int c) { return cells.get(c); }
  }

  static class XCell implements Cell {
    private final String t;       // t attribute ("n" when absent)
    private final String v;       // v element text (cached value), or null
    private final boolean formula;
    private final String inline;  // text of an inline string, or null

    XCell(XSSFWorkbook wb, Element ce) {
      t = ce.hasAttribute("t") ? ce.getAttribute("t") : "n";
      Element f = XSSFWorkbook.child(ce, "f"), ve = XSSFWorkbook.child(ce, "v"), is = XSSFWorkbook.child(ce, "is");
      formula = f != null && !"dataTable".equals(f.getAttribute("t"));
      String value = ve == null ? null : ve.getTextContent();
      if ("s".equals(t) && value != null) value = wb.sharedStrings.get(Integer.parseInt(value.trim()));
      v = value;
      inline = is == null ? null : XSSFWorkbook.text(is);
    }

    /** Type of the value stored in the file (for a formula: of its cached result). */
    CellType cachedType() {
      switch (t) {
        case "s": case "str": case "inlineStr": return CellType.STRING;
        case "b": return CellType.BOOLEAN;
        case "e": return CellType.ERROR;
        default: return v == null && !formula ? CellType.BLANK : CellType.NUMERIC;
      }
    }

    @Override public CellType getCellType() { return formula ? CellType.FORMULA : cachedType(); }

    @Override public String getStringCellValue() {
      CellType c = cachedType();
      if (c == CellType.BLANK) return "";
      if (c != CellType.STRING) throw new IllegalStateException("Cannot get a STRING value from a " + c + " cell");
      return "inlineStr".equals(t) ? (inline == null ? "" : inline) : (v == null ? "" : v);
    }

    @Override public double getNumericCellValue() {
      CellType c = cachedType();
      if (c == CellType.BLANK) return 0.0;
      if (c != CellType.NUMERIC) throw new IllegalStateException("Cannot get a NUMERIC value from a " + c + " cell");
      return v == null || v.isEmpty() ? 0.0 : Double.parseDouble(v);
    }
  }
}
