"""``report.html``: report.md as one self-contained HTML file, readable offline.

The report's Markdown is armfit's own, in a small subset (headings, paragraphs, bulleted
and numbered lists, pipe tables, fenced code, images, ``**bold**`` and ``code``), so it is
converted here rather than by a Markdown library. Every figure is embedded as a data URI;
the style sheet is inline; the page loads nothing else.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Callable, Iterator
from pathlib import Path

__all__ = ["report_html"]

_STYLE = """
body { font: 15px/1.5 system-ui, -apple-system, "Segoe UI", sans-serif; color: #1d1d1f;
       max-width: 1100px; margin: 2em auto; padding: 0 1.5em; }
h1 { font-size: 1.7em; border-bottom: 2px solid #ccc; padding-bottom: .2em; }
h2 { font-size: 1.35em; margin-top: 2em; border-bottom: 1px solid #ddd; }
h3 { font-size: 1.1em; margin-top: 1.6em; }
code, pre { font: 13px/1.4 ui-monospace, "DejaVu Sans Mono", monospace;
            background: #f4f4f6; border-radius: 3px; }
code { padding: 0 .25em; }
pre { padding: .7em 1em; overflow-x: auto; }
table { border-collapse: collapse; margin: .8em 0; font-size: 13px; display: block;
        overflow-x: auto; }
th, td { border: 1px solid #d0d0d6; padding: .25em .55em; text-align: left;
         vertical-align: top; }
th { background: #eef0f4; }
tr:nth-child(even) td { background: #fafafc; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
figure { margin: 1em 0 2em; }
figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 13px; color: #555; }
nav { font-size: 13px; background: #f7f7f9; padding: .6em 1em; border-radius: 4px;
      display: flex; flex-wrap: wrap; gap: .3em 1.2em; }
"""

_IMAGE = re.compile(r"^!\[(?P<alt>[^\]]*)\]\((?P<src>[^)\s]+)\)$")
_MARKER = re.compile(r"^(- |\d+\. )")
_NUMBER = re.compile(r"^[−\-+]?[\d.,]+(e[−\-+]?\d+)?[†‡]?$|^–$")


def _inline(text: str) -> str:
    """HTML of one line of text: escaped, with ``code`` and **bold**."""
    parts = re.split(r"(`[^`]*`)", text)
    out = []
    for part in parts:
        if len(part) >= 2 and part.startswith("`") and part.endswith("`"):
            out.append(f"<code>{html.escape(part[1:-1])}</code>")
        else:
            esc = html.escape(part)
            out.append(re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", esc))
    return "".join(out)


def _slug(text: str, seen: dict[str, int]) -> str:
    """An id for a heading: lower-case words joined by '-', unique in the page."""
    base = re.sub(r"[^\w]+", "-", text.lower()).strip("-") or "section"
    n = seen.get(base, 0)
    seen[base] = n + 1
    return base if n == 0 else f"{base}-{n}"


_CELL_SPLIT = re.compile(r"(?<!\\)\|")


def _cells(line: str) -> list[str]:
    """The cells of a pipe-table row; a ``\\|`` (how :func:`armfit.report.md_table`
    writes a ``|`` in a cell) is a character of its cell."""
    inner = line.strip()[1:-1]
    return [c.strip().replace("\\|", "|") for c in _CELL_SPLIT.split(inner)]


def _table(rows: list[str]) -> str:
    """A pipe table (header, separator, rows) as HTML; numeric cells right-aligned."""
    head = "".join(f"<th>{_inline(c)}</th>" for c in _cells(rows[0]))
    body = []
    for line in rows[2:]:
        tds = "".join(f'<td class="num">{_inline(c)}</td>' if _NUMBER.match(c)
                      else f"<td>{_inline(c)}</td>" for c in _cells(line))
        body.append(f"<tr>{tds}</tr>")
    return (f"<table><thead><tr>{head}</tr></thead><tbody>" + "".join(body)
            + "</tbody></table>")


def _image(folder: Path, src: str) -> tuple[str, int | None]:
    """The image ``folder / src`` as a data URI (PNG or SVG by its extension), and the
    width to show it at, CSS px: half a PNG's pixels (figures are drawn at 300 dpi, so a
    one-column figure is not blown up to the page's width), None for another kind."""
    data = (folder / src).read_bytes()
    suffix = Path(src).suffix.lower()
    kind = {".png": "image/png", ".svg": "image/svg+xml"}.get(suffix,
                                                              "application/octet-stream")
    # a PNG's width: the first field of its IHDR chunk, bytes 16-20 (PNG specification)
    width = (max(1, int.from_bytes(data[16:20], "big") // 2)
             if suffix == ".png" and data[12:16] == b"IHDR" else None)
    return f"data:{kind};base64," + base64.b64encode(data).decode("ascii"), width


def _blocks(lines: list[str]) -> Iterator[tuple[str, list[str]]]:
    """The Markdown's blocks in order: (kind, lines) with kind one of heading, code,
    table, ul, ol, image, para."""
    i = 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if line.startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            yield "code", lines[i + 1:j]
            i = j + 1
            continue
        kind = ("heading" if line.startswith("#") else "table" if line.startswith("|")
                else "ul" if line.startswith("- ") else "image" if _IMAGE.match(line)
                else "ol" if re.match(r"^\d+\. ", line) else "para")
        if kind in ("heading", "image"):
            yield kind, [line]
            i += 1
            continue
        j = i + 1
        while j < len(lines) and lines[j].strip() and not lines[j].startswith(("```", "#")):
            nxt = lines[j]
            if kind in ("table",) and not nxt.startswith("|"):
                break
            if kind == "para" and (nxt.startswith(("|", "- ")) or re.match(r"^\d+\. ", nxt)):
                break
            j += 1
        yield kind, lines[i:j]
        i = j


def _render(kind: str, block: list[str], image: Callable[[str], tuple[str, int | None]],
            seen: dict[str, int]) -> str:
    """The HTML of one block."""
    if kind == "heading":
        level = len(block[0]) - len(block[0].lstrip("#"))
        text = block[0][level:].strip()
        return f'<h{level} id="{_slug(text, seen)}">{_inline(text)}</h{level}>'
    if kind == "code":
        return "<pre><code>" + html.escape("\n".join(block)) + "</code></pre>"
    if kind == "table":
        return _table(block)
    if kind in ("ul", "ol"):
        items = "".join(f"<li>{_inline(_MARKER.sub('', ln))}</li>" for ln in block)
        return f"<{kind}>{items}</{kind}>"
    if kind == "image":
        m = _IMAGE.match(block[0])
        alt = html.escape(m["alt"], quote=True)
        uri, width = image(m["src"])
        size = "" if width is None else f' width="{width}"'
        return (f'<figure><img src="{uri}"{size} alt="{alt}">'
                f"<figcaption>{_inline(m['alt'])}</figcaption></figure>")
    return "<p>" + " ".join(_inline(ln) for ln in block) + "</p>"


def report_html(markdown: str, folder: str | Path, *, title: str = "armfit report") -> str:
    """report.md's text as one self-contained HTML page.

    Parameters
    ----------
    markdown : str
        The report's Markdown (:func:`armfit.report.report_markdown`).
    folder : path
        The folder the Markdown's image paths are relative to (the run's OUTDIR); every
        image is read from there and embedded as a data URI.
    title : str
        The page's title.

    Returns
    -------
    str
        The HTML document: inline style, embedded images, a table of contents of the
        second-level headings; no script and nothing loaded from elsewhere.
    """
    folder = Path(folder)
    seen: dict[str, int] = {}
    body = [_render(kind, block, lambda src: _image(folder, src), seen)
            for kind, block in _blocks(markdown.splitlines())]
    toc = [(m[1], m[2]) for m in (re.match(r'<h2 id="([^"]+)">(.*)</h2>', b) for b in body)
           if m]
    nav = ("<nav>" + "".join(f'<a href="#{i}">{t}</a>' for i, t in toc) + "</nav>"
           if toc else "")
    if body and body[0].startswith("<h1"):
        body.insert(1, nav)
    else:
        body.insert(0, nav)
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
            f"<title>{html.escape(title)}</title>\n<style>{_STYLE}</style>\n</head>\n"
            "<body>\n" + "\n".join(body) + "\n</body>\n</html>\n")
