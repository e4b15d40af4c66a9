"""``report.html``: the Markdown report rendered for a browser, beside ``report.md``.

One self-contained page (style inline, no script, nothing fetched from the network) that
references the report's ``figures/``, ``tables/`` and ``galleries/`` by relative paths, so the
folder can be moved and opened from ``file://``. Links ``scene_3d.html`` (the interactive 3D
view) when that file is in the folder as the page is written.
"""

from __future__ import annotations

from pathlib import Path

import jinja2
import markdown
from markupsafe import Markup

#: Pages of the report folder linked at the top of the page when present: name -> label.
COMPANIONS = {"scene_3d.html": "3D view of the scene"}
#: Python-Markdown extensions: GitHub-style tables, heading anchors, lists as GitHub draws them.
EXTENSIONS = ["tables", "toc", "sane_lists"]

PAGE = jinja2.Environment(autoescape=True).from_string(
    """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{{ title }}</title>
<link rel="icon" href="data:,">
<style>
body { font-family: system-ui, sans-serif; margin: 0 auto; max-width: 1400px; padding: 1rem 2rem; color: #1f2328; }
nav { padding: 0.5rem 0; border-bottom: 1px solid #d0d7de; margin-bottom: 1rem; }
nav a { margin-right: 1.5rem; }
table { border-collapse: collapse; margin: 0.5rem 0 1.5rem; font-size: 0.9rem; display: block;
        max-width: 100%; overflow-x: auto; }
th, td { border: 1px solid #d0d7de; padding: 0.25rem 0.5rem; vertical-align: top; }
th { background: #f6f8fa; }
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
    title = next((line[2:].strip() for line in text.splitlines() if line.startswith("# ")), markdown_path.stem)
    body = markdown.markdown(text, extensions=EXTENSIONS, output_format="html")
    links = [(name, label) for name, label in COMPANIONS.items() if (html_path.parent / name).is_file()]
    if markdown_path.parent == html_path.parent:
        links.append((markdown_path.name, "Markdown version"))
    html_path.write_text(PAGE.render(title=title, body=Markup(body), links=links))
    return html_path
