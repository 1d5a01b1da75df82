"""The configuration reference page, generated from ``workflow/schemas/config.schema.yaml``.

An MkDocs hook: ``on_files`` adds the page ``reference/config.md`` to every build, rendered
from the schema the workflow validates each study config against, so the page cannot
disagree with what the workflow accepts (there is no committed copy to go stale).
``render(schema)`` is the pure function; ``tests/test_docs.py`` checks it covers every key.
Run ``python docs/hooks/config_reference.py`` to print the page.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
PAGE = "reference/config.md"
BOUNDS = {"minimum": ">= {}", "exclusiveMinimum": "> {}", "maximum": "<= {}",
          "exclusiveMaximum": "< {}", "minItems": "at least {} items",
          "maxItems": "at most {} items", "minProperties": "at least {} entries",
          "pattern": "matches `{}`"}  # fmt: skip

HEADER = """# Configuration reference

A study is one YAML file (`config/config.yaml` is the default study; pass another with
`snakemake --configfile FILE`). Every key below is checked against the schema
`workflow/schemas/config.schema.yaml` when the workflow starts, before anything is computed;
a misspelt key, a wrong type or a value out of range stops the run with one line naming the
key. This page is generated from that schema at every build of the documentation.

Options of a test method (`testing.methods.<method>`) and twin specifications are further
checked by the library when the config is read; see
[the statistics](../explanation/statistics.md) and [twins](../how-to/twins.md).
"""


def _type(node: dict[str, Any]) -> str:
    if "enum" in node:
        return "one of " + ", ".join(f"`{v}`" for v in node["enum"])
    if "oneOf" in node:
        return " or ".join(_type(n) for n in node["oneOf"])
    t = node.get("type", "")
    t = " or ".join(t) if isinstance(t, list) else t
    if t == "array" and isinstance(node.get("items"), dict):
        t = f"array of ({_type(node['items'])})"
    return t


def _limits(node: dict[str, Any]) -> str:
    parts = [fmt.format(node[k]) for k, fmt in BOUNDS.items() if k in node]
    if node.get("uniqueItems"):
        parts.append("no repeats")
    items = node.get("items")
    if isinstance(items, dict) and "enum" not in items:
        parts += [f"each {p}" for p in _limits(items).split("; ") if p]
    return "; ".join(parts)


def _links(text: str) -> str:
    """``docs/x/y.md`` in a schema description becomes a link relative to this page; ``<``
    and ``>`` are escaped (``results/<study>/`` is text, not an HTML tag)."""
    text = text.replace("<", "&lt;").replace(">", "&gt;")
    return re.sub(r"docs/([\w/-]+\.md)", r"[\1](../\1)", text)


def rows(node: dict[str, Any], path: str, required: set[str]) -> list[tuple[str, ...]]:
    """(key path, type, limits, default, required, description) for ``node`` and below."""
    out = []
    if path:
        default = node.get("default")
        out.append((f"`{path}`", _type(node).replace("|", "\\|"), _limits(node),
                    "" if default is None else f"`{default}`",
                    "yes" if path.rsplit(".", 1)[-1] in required else "",
                    _links(node.get("description", ""))))  # fmt: skip
    props = node.get("properties", {})
    req = set(node.get("required", []))
    for key, sub in props.items():
        out += rows(sub, f"{path}.{key}" if path else key, req)
    extra = node.get("additionalProperties")
    if isinstance(extra, dict) and extra.get("type") == "object" and extra.get("properties"):
        out += rows(extra, f"{path}.<name>", set())
    return out


def render(schema: dict[str, Any]) -> str:
    """The reference page in Markdown: one table per top-level section of the schema."""
    lines = [HEADER]
    top_req = set(schema.get("required", []))
    for key, sub in schema["properties"].items():
        lines.append(f"## `{key}`\n")
        if sub.get("description"):
            lines.append(_links(sub["description"]) + "\n")
        lines.append("| key | type | limits | default | required | meaning |")
        lines.append("|---|---|---|---|---|---|")
        for r in rows(sub, key, top_req):
            lines.append("| " + " | ".join(r) + " |")
        lines.append("")
    return "\n".join(lines)


def load_schema(path: Path = SCHEMA) -> dict[str, Any]:
    return yaml.safe_load(path.read_text())


def on_files(files, config):  # noqa: ANN001 (MkDocs hook signature)
    """Add the generated page to the build (MkDocs >= 1.6)."""
    from mkdocs.structure.files import File

    files.append(File.generated(config, PAGE, content=render(load_schema())))
    return files


if __name__ == "__main__":
    print(render(load_schema()))
