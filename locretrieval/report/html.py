"""``report.html``: the Markdown report rendered for a browser, beside ``report.md`` (`write_html`);
a page of interactive plotly figures (`write_figures_page`: a sweep's Optuna figures).

One self-contained page (style inline, no script, nothing fetched from the network) that
references the report's ``figures/``, ``tables/`` and ``galleries/`` by relative paths, so the
folder can be moved and opened from ``file://``. Links ``scene_3d.html`` (the interactive 3D
view) when that file is in the folder as the page is written.

The Markdown escapes every string from data (`locretrieval.report.markdown`); the HTML Python-Markdown
makes of it is then cleaned by a sanitizer's allowlist (`nh3`: the tags and attributes of
`ALLOWED_TAGS`, relative and http(s) links only, no script, no event handler, no style but a
cell's alignment) and the page carries a Content-Security-Policy (`CONTENT_SECURITY_POLICY`)
that runs no script at all.
"""

from __future__ import annotations

import base64
import hashlib
import re
from collections.abc import Sequence
from html import unescape
from pathlib import Path
from typing import Any

import jinja2
import markdown
import nh3
from markupsafe import Markup

#: Pages of the report folder linked at the top of the page when present: name -> label.
COMPANIONS = {"scene_3d.html": "3D view of the scene"}
#: Python-Markdown extensions: GitHub-style tables, heading anchors, lists as GitHub draws them.
EXTENSIONS = ["tables", "toc", "sane_lists"]
#: What the report's Markdown makes (and nothing else): tags -> their attributes kept.
ALLOWED_TAGS: dict[str, set[str]] = {
    **{f"h{level}": {"id"} for level in range(1, 7)},
    **{tag: set() for tag in ("p", "ul", "ol", "li", "strong", "em", "code", "pre", "br", "hr", "blockquote")},
    **{tag: set() for tag in ("table", "thead", "tbody", "tr")},
    **{tag: {"style"} for tag in ("th", "td")},  # text-align only (filter below)
    "a": {"href", "title"},
    "img": {"src", "alt", "title"},
}
#: The policy of every page the report writes that has no script: images from the report's folder,
#: its own inline style; no script, no object, no frame, no form, nothing from the network.
CONTENT_SECURITY_POLICY = (
    "default-src 'none'; img-src 'self' file: data:; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"
)

PAGE = jinja2.Environment(autoescape=True).from_string(
    """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="{{ policy }}">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{{ title }}</title>
<link rel="icon" href="data:,">
<style>
body { font-family: system-ui, sans-serif; margin: 0 auto; max-width: 1400px; padding: 1rem 2rem; color: #1f2328;
       overflow-wrap: anywhere; }
nav { padding: 0.5rem 0; border-bottom: 1px solid #d0d7de; margin-bottom: 1rem; }
nav a { margin-right: 1.5rem; }
table { border-collapse: collapse; margin: 0.5rem 0 1.5rem; font-size: 0.9rem; display: block;
        max-width: 100%; overflow-x: auto; }
th, td { border: 1px solid #d0d7de; padding: 0.25rem 0.5rem; vertical-align: top; }
th { background: #f6f8fa; min-width: 6ch; }
img { max-width: 100%; height: auto; }
code { font-size: 0.85em; }
</style>
</head>
<body>
{% if links %}<nav>{% for href, label in links %}<a href="{{ href }}">{{ label }}</a>{% endfor %}</nav>{% endif %}
{{ body }}
</body>
</html>
"""
)


def write_html(markdown_path: Path, html_path: Path | None = None) -> Path:
    """Render ``markdown_path`` (a report's ``report.md``) to ``html_path`` (default: the same
    name with ``.html``), its relative links kept; returns the path written."""
    html_path = html_path or markdown_path.with_suffix(".html")
    text = markdown_path.read_text()
    title = next(
        (unescape(line[2:].strip()) for line in text.splitlines() if line.startswith("# ")), markdown_path.stem
    )
    body = sanitized(markdown.markdown(text, extensions=EXTENSIONS, output_format="html"))
    links = [(name, label) for name, label in COMPANIONS.items() if (html_path.parent / name).is_file()]
    if markdown_path.parent == html_path.parent:
        links.append((markdown_path.name, "Markdown version"))
    page = PAGE.render(title=title, body=Markup(body), links=links, policy=Markup(CONTENT_SECURITY_POLICY))
    html_path.write_text(page)
    return html_path


FIGURES_PAGE = jinja2.Environment(autoescape=True).from_string(
    """<!DOCTYPE html>
<html lang="en">
<head><meta charset="utf-8"><title>{{ title }}</title></head>
<body>
<h1>{{ title }}</h1>
{{ figures }}
</body>
</html>
"""
)


def write_figures_page(path: Path, title: str, figures: Sequence[Any]) -> Path:
    """Write the plotly ``figures`` under the heading ``title`` (text, escaped) as one self-contained
    page: plotly.js embedded once, nothing fetched, its own scripts only (`with_script_policy`);
    returns ``path``."""
    parts = [figure.to_html(full_html=False, include_plotlyjs=index == 0) for index, figure in enumerate(figures)]
    page = FIGURES_PAGE.render(title=title, figures=Markup("\n".join(parts)))
    path.write_text(with_script_policy(page), encoding="utf-8")  # its own scripts only: names are data
    return path


#: An inline script of a page the project writes (plotly's: ``<script type="text/javascript">...</script>``).
_INLINE_SCRIPT = re.compile(r"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.DOTALL | re.IGNORECASE)


def with_script_policy(page: str) -> str:
    """``page`` (a full HTML document the project generated, such as plotly's) with a
    Content-Security-Policy meta as the first element of its ``<head>`` that allows exactly its
    own inline scripts, by their SHA-256 (a script injected by data would not match), and nothing
    from the network; its inline styles and the data/blob URLs a WebGL plot makes stay allowed."""
    digests = [
        "'sha256-" + base64.b64encode(hashlib.sha256(script.encode()).digest()).decode() + "'"
        for script in _INLINE_SCRIPT.findall(page)
    ]
    scripts = " ".join(digests) or "'none'"
    policy = (
        f"default-src 'none'; script-src {scripts}; "
        "style-src 'unsafe-inline'; img-src data: blob:; font-src data:; worker-src blob:; "
        "base-uri 'none'; form-action 'none'"
    )
    head = re.search(r"<head[^>]*>", page, re.IGNORECASE)
    if head is None:
        raise ValueError("with_script_policy: the page has no <head>")
    meta = f'\n<meta http-equiv="Content-Security-Policy" content="{policy}">'
    return page[: head.end()] + meta + page[head.end() :]


def sanitized(html: str) -> str:
    """``html`` with only `ALLOWED_TAGS` and their attributes, links relative or http(s), styles
    only ``text-align`` (nh3, the Ammonia sanitizer's allowlist): safe to mark as `Markup`."""
    return nh3.clean(
        html,
        tags=set(ALLOWED_TAGS),
        attributes=ALLOWED_TAGS,
        url_schemes={"http", "https"},
        filter_style_properties={"text-align"},
    )
