// twinfalsify stand-in for the part of Apache POI's XSSFWorkbook that Pulse's DataSetReader uses:
// reads an .xlsx (a zip of XML parts) with the JDK only. Formulas are not evaluated: the result
// cached in the file by the spreadsheet program is returned (Pulse's Data.xlsx is saved by Excel).
package org.apache.poi.xssf.usermodel;

import java.io.ByteArrayInputStream;
import java.io.Closeable;
import java.io.IOException;
import java.io.InputStream;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import java.util.zip.ZipEntry;
import java.util.zip.ZipInputStream;
import javax.xml.parsers.DocumentBuilderFactory;
import org.apache.poi.ss.usermodel.Cell;
import org.apache.poi.ss.usermodel.CellType;
import org.apache.poi.ss.usermodel.FormulaEvaluator;
import org.w3c.dom.Document;
import org.w3c.dom.Element;
import org.w3c.dom.Node;
import org.w3c.dom.NodeList;

public class XSSFWorkbook implements Closeable {
  private final Map<String, byte[]> parts = new HashMap<>();
  private final Map<String, String> sheetPaths = new HashMap<>(); // lower-case name -> zip path
  private final Map<String, XSSFSheet> sheets = new HashMap<>();
  final List<String> sharedStrings = new ArrayList<>();

  public XSSFWorkbook(InputStream in) throws IOException {
    try (ZipInputStream zip = new ZipInputStream(in)) {
      for (ZipEntry e; (e = zip.getNextEntry()) != null; )
        if (!e.isDirectory()) parts.put(e.getName(), zip.readAllBytes());
    }
    Map<String, String> rels = new HashMap<>(); // relationship id -> zip path
    String strings = "xl/sharedStrings.xml";
    for (Element r : elements(xml("xl/_rels/workbook.xml.rels").getDocumentElement(), "Relationship")) {
      String t = r.getAttribute("Target");
      String path = t.startsWith("/") ? t.substring(1) : "xl/" + t;
      rels.put(r.getAttribute("Id"), path);
      if (r.getAttribute("Type").endsWith("/sharedStrings")) strings = path;
    }
    for (Element s : elements(xml("xl/workbook.xml").getDocumentElement(), "sheet"))
      sheetPaths.put(s.getAttribute("name").toLowerCase(), rels.get(relId(s)));
    if (parts.containsKey(strings))
      for (Element si : elements(xml(strings).getDocumentElement(), "si"))
        sharedStrings.add(text(si));
  }

  /** Sheet by name (case-insensitive, as in POI), or null. */
  public XSSFSheet getSheet(String name) {
    String key = name.toLowerCase();
    if (!sheetPaths.containsKey(key)) return null;
    return sheets.computeIfAbsent(key, k -> new XSSFSheet(this, xml(sheetPaths.get(k))));
  }

  public Helper getCreationHelper() { return new Helper(); }

  public static class Helper {
    public FormulaEvaluator createFormulaEvaluator() {
      return (Cell c) -> c.getCellType() == CellType.FORMULA ? ((XSSFSheet.XCell) c).cachedType() : CellType._NONE;
    }
  }

  @Override public void close() {}

  Document xml(String part) {
    byte[] b = parts.get(part);
    if (b == null) throw new IllegalArgumentException("no part " + part + " in the workbook");
    try {
      DocumentBuilderFactory f = DocumentBuilderFactory.newInstance();
      f.setNamespaceAware(true);
      return f.newDocumentBuilder().parse(new ByteArrayInputStream(b));
    } catch (Exception ex) {
      throw new IllegalStateException("cannot parse " + part + ": " + ex, ex);
    }
  }

  /** Descendant elements with this local name, in document order. */
  static List<Element> elements(Element root, String local) {
    List<Element> out = new ArrayList<>();
    NodeList l = root.getElementsByTagNameNS("*", local);
    for (int i = 0; i < l.getLength(); i++) out.add((Element) l.item(i));
    return out;
  }

  /** First child element with this local name, or null. */
  static Element child(Element e, String local) {
    for (Node n = e.getFirstChild(); n != null; n = n.getNextSibling())
      if (n instanceof Element && local.equals(n.getLocalName())) return (Element) n;
    return null;
  }

  /** Text of a shared or inline string: all t elements except phonetic runs (rPh), _xHHHH_ decoded. */
  static String text(Element si) {
    StringBuilder sb = new StringBuilder();
    for (Element t : elements(si, "t"))
      if (!"rPh".equals(t.getParentNode().getLocalName())) sb.append(t.getTextContent());
    StringBuilder out = new StringBuilder();
    java.util.regex.Matcher m = java.util.regex.Pattern.compile("_x([0-9A-Fa-f]{4})_").matcher(sb);
    while (m.find()) m.appendReplacement(out, java.util.regex.Matcher.quoteReplacement(
        String.valueOf((char) Integer.parseInt(m.group(1), 16))));
    m.appendTail(out);
    return out.toString();
  }

  private static String relId(Element sheet) {
    for (int i = 0; i < sheet.getAttributes().getLength(); i++) {
      Node a = sheet.getAttributes().item(i);
      if ("id".equals(a.getLocalName()) && a.getNamespaceURI() != null) return a.getNodeValue();
    }
    throw new IllegalStateException("sheet without r:id: " + sheet.getAttribute("name"));
  }
}
