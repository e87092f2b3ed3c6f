"""The HTML pages (the report, the sweep's family page): one self-contained page with its
pictures copied beside it, and the pieces every section uses."""

from __future__ import annotations

import html
import shutil
from pathlib import Path

from models.io import atomic_path


def img_tag(out: Path, src: Path, alt: str, copy: bool = True) -> str:
    """An ``<img>`` for the page in ``out``: ``src`` copied beside it, or (``copy=False``,
    ``src`` under ``out``) linked where it lies."""
    if not src.exists():
        return f"<p class=missing>missing picture: {html.escape(str(src))}</p>"
    if not copy:
        return f'<img src="{html.escape(src.relative_to(out).as_posix())}" alt="{html.escape(alt)}">'
    dst = out / (src.parent.name + "_" + src.name if src.parent != out else src.name)
    if src.resolve() != dst.resolve():
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
    return f'<img src="{html.escape(dst.name)}" alt="{html.escape(alt)}">'


def not_run(command: str) -> str:
    """A section's place when the command that makes it has not run."""
    return f"<p class=missing>Not run yet: <code>{html.escape(command)}</code>.</p>"


def html_page(name: str, sections) -> str:
    """The page: a title, a table of contents and ``sections``, ``[(title, html body)]``."""
    toc = "".join(f'<li><a href="#s{k}">{html.escape(t)}</a></li>' for k, (t, _) in enumerate(sections))
    body = "".join(f'<section id="s{k}"><h2>{html.escape(t)}</h2>{b}</section>' for k, (t, b) in enumerate(sections))
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>bcsdf report: {html.escape(name)}</title>
<style>
body {{ font: 15px/1.45 system-ui, sans-serif; max-width: 1200px; margin: 2em auto; padding: 0 1em; color: #222; }}
img {{ max-width: 100%; display: block; margin: 0.6em 0; border: 1px solid #ddd; }}
table {{ border-collapse: collapse; margin: 0.8em 0; font-size: 13px; }}
td, th {{ border: 1px solid #ccc; padding: 2px 8px; text-align: right; }}
th {{ background: #f3f3f3; }} pre {{ background: #f7f7f7; padding: 1em; overflow: auto; font-size: 12px; }}
.missing {{ color: #a33; }}
</style></head><body>
<h1>Fiber bundle scattering: {html.escape(name)}</h1>
<ol>{toc}</ol>
{body}
<script>
// self-check for headless browsers: how many pictures, how many failed to load
window.addEventListener("load", () => {{
  const imgs = Array.from(document.images);
  document.body.dataset.images = imgs.length;
  document.body.dataset.broken = imgs.filter(i => !i.complete || i.naturalWidth === 0).length;
}});
</script>
</body></html>
"""
