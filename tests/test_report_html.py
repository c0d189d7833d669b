"""armfit.htmlreport: report.md as one self-contained HTML page (the page of a real run is
opened in headless Chromium by tests/test_cli_run.py)."""

from __future__ import annotations

import base64
import re
from html.parser import HTMLParser

from armfit.htmlreport import report_html

#: the smallest valid PNG: 1x1 pixel, greyscale (bytes of the PNG specification's layout,
#: RFC 2083: signature, IHDR, IDAT of one zlib-compressed row, IEND)
PNG_1X1 = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAAAAAA6fptVAAAACklEQVR4nGNgAAAAAgABSK+kcQAAAABJRU5ErkJggg==")

MARKDOWN = """# armfit report

```
armfit run raw -o 'out/my run' --method h1
```

## Tables

Fits to **the mean**; see `grip_params.csv` & <notes>.

| axis | Ma (kg) | note |
|---|---|---|
| x | 0.05000† | a <b> tag, a \\| bar |
| z | -3.038 | – |

1. **ingest** — 27 trial(s)
2. **estimate** — done

- first
- second

## Figures

![Fig. 5 <bode>](figures/bode.png)
"""


class _Collect(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def _page(tmp_path) -> tuple[str, _Collect]:
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "bode.png").write_bytes(PNG_1X1)
    page = report_html(MARKDOWN, tmp_path)
    parsed = _Collect()
    parsed.feed(page)
    return page, parsed


def test_images_are_embedded_byte_for_byte_and_nothing_is_loaded_from_elsewhere(tmp_path):
    page, parsed = _page(tmp_path)
    imgs = [a for t, a in parsed.tags if t == "img"]
    assert len(imgs) == 1
    head, data = imgs[0]["src"].split(",", 1)
    assert head == "data:image/png;base64" and base64.b64decode(data) == PNG_1X1
    assert imgs[0]["alt"] == "Fig. 5 <bode>"             # the caption, unescaped by the parser
    # shown at half its pixels (300 dpi figures), never 0: the 1-pixel image at 1 px
    assert imgs[0]["width"] == "1"
    # no script, no stylesheet or font fetched, links only within the page
    assert not any(t in ("script", "link", "iframe") for t, _ in parsed.tags)
    assert all(a["href"].startswith("#") for t, a in parsed.tags if t == "a")
    assert "url(" not in page and "@import" not in page


def test_text_is_escaped_and_the_markdown_subset_is_rendered(tmp_path):
    page, parsed = _page(tmp_path)
    assert "&lt;notes&gt;" in page and "<b>" not in page
    # md_table writes a | in a cell as \| (armfit.report): one cell, the bar restored
    assert "<td>a &lt;b&gt; tag, a | bar</td>" in page
    assert "<strong>the mean</strong>" in page and "<code>grip_params.csv</code>" in page
    assert "<pre><code>armfit run raw -o &#x27;out/my run&#x27; --method h1</code></pre>" in page
    tags = [t for t, _ in parsed.tags]
    assert tags.count("table") == 1 and tags.count("th") == 3 and tags.count("td") == 6
    assert tags.count("ol") == 1 and tags.count("ul") == 1 and tags.count("li") == 4
    # numbers (a mark after one, a dash for none) right-aligned; words left
    assert re.findall(r'<td class="num">([^<]*)</td>', page) == ["0.05000†", "-3.038", "–"]
    # a table of contents of the second-level headings, linked to their ids
    assert re.findall(r'<a href="#([^"]+)">', page) == ["tables", "figures"]
    assert '<h2 id="tables">' in page and '<h2 id="figures">' in page
