// Typesets the formulas of a page with the KaTeX copy served by the site itself (no network).
// pymdownx.arithmatex (generic mode) leaves inline maths as <span class="arithmatex">\(...\)</span>
// and display maths as <div class="arithmatex">\[...\]</div>; each is replaced by KaTeX's HTML.
// throwOnError: false turns a formula KaTeX cannot parse into a visible .katex-error node
// (tests/docs/test_docs_maths.py fails on one) instead of leaving the page half rendered.
(function () {
  "use strict";
  function render(root) {
    root.querySelectorAll(".arithmatex").forEach(function (el) {
      var tex = el.textContent.trim();
      var display = el.tagName === "DIV";
      if (tex.startsWith("\\(") || tex.startsWith("\\[")) tex = tex.slice(2, -2);
      katex.render(tex, el, { displayMode: display, throwOnError: false, strict: "ignore" });
    });
  }
  if (typeof document$ !== "undefined") {
    document$.subscribe(function () { render(document.body); });  // Material's page loads
  } else {
    render(document.body);
  }
})();
