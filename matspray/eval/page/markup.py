"""The report page around its sections: the style, the image viewer (a click on any picture opens it enlarged to the
window, Escape or a click closes it), the figures written as PNGs beside the page, and the markdown subset the tables
are written in."""

from __future__ import annotations

import html
from pathlib import Path

import torch

from matspray.data import write_image
from matspray.data.images import srgb_to_linear
from matspray.eval.page.paths import without_machine_paths

STYLE = """
body { font-family: system-ui, sans-serif; margin: 1em auto; max-width: 1240px; padding: 0 12px; color: #222; }
h1 { font-size: 1.5em; margin: 0.2em 0 0.4em; } h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; } \
td, th { border: 1px solid #ccc; padding: 3px 8px; text-align: center; }
figure { display: inline-block; margin: 4px; text-align: center; vertical-align: top; }
figcaption { font-size: 0.8em; color: #555; max-width: 320px; margin: auto; }
img { image-rendering: pixelated; width: 160px; cursor: zoom-in; \
background: repeating-conic-gradient(#ddd 0% 25%, #fff 0% 50%) 50% / 16px 16px; }
img.env { width: 296px; image-rendering: auto; } img.strip { width: auto; height: 240px; }
.warn { background: #fff3cd; padding: 0.4em 0.6em; border: 1px solid #e0c060; margin: 0.3em 0; }
.summary { display: flex; gap: 20px; align-items: flex-start; }
.summary table { margin: 0.2em 0 0.6em; font-size: 0.92em; } .summary h2 { margin-top: 0.2em; font-size: 1.1em; }
.relit-grid { display: grid; gap: 2px 6px; align-items: center; } .relit-grid img { width: var(--picture, 200px); }
.note { font-size: 0.8em; color: #555; }
.relit-grid .rowlabel { font-size: 0.85em; color: #555; writing-mode: vertical-rl; transform: rotate(180deg); }
.verdicts { margin: 0; padding-left: 1.2em; font-size: 0.92em; } .verdicts li { margin: 0.15em 0; }
.disagrees { color: #8a1c00; } .agrees { color: #1d5e20; }
dl.glossary dt { font-weight: bold; margin-top: 0.5em; } dl.glossary dd { margin-left: 1.5em; }
#viewer { position: fixed; inset: 0; background: rgba(0, 0, 0, 0.88); z-index: 10; cursor: zoom-out; \
display: flex; flex-direction: column; align-items: center; justify-content: center; }
#viewer[hidden] { display: none; }
#viewer img { background-size: 32px 32px; cursor: zoom-out; }
#viewer p { color: #eee; margin: 0.6em; }
"""

# the image viewer: one overlay for the whole page, filled from the clicked picture; the picture is scaled to fill
# 95 % of the window's width or 85 % of its height, whichever comes first, and keeps the thumbnail's pixelation
# (a 40 px test view shows its pixels, a light's smooth preview stays smooth)
VIEWER = """
<div id="viewer" hidden><img id="viewer-image" alt=""><p id="viewer-caption"></p></div>
<script>
(function () {
  const viewer = document.getElementById("viewer"), big = document.getElementById("viewer-image"),
        caption = document.getElementById("viewer-caption");
  function open(img) {
    const scale = Math.min(0.95 * innerWidth / img.naturalWidth, 0.85 * innerHeight / img.naturalHeight);
    big.src = img.src;
    big.className = img.className;
    big.style.width = Math.round(img.naturalWidth * scale) + "px";
    big.style.height = Math.round(img.naturalHeight * scale) + "px";
    caption.textContent = img.alt + " (" + img.naturalWidth + " x " + img.naturalHeight + " px)";
    viewer.hidden = false;
  }
  document.addEventListener("click", function (event) {
    if (!viewer.hidden) { viewer.hidden = true; return; }
    if (event.target.tagName === "IMG" && event.target.id !== "viewer-image") open(event.target);
  });
  document.addEventListener("keydown", function (event) { if (event.key === "Escape") viewer.hidden = true; });
})();
</script>
"""


def html_page(sections: list[str], title: str = "MatSpray report", places: dict | None = None) -> str:
    """The page around its sections, with the image viewer; `places` ({absolute path: what to write instead}) and
    any other absolute path are kept off it (`without_machine_paths`)."""
    page = (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{STYLE}</style></head><body>{''.join(sections)}{VIEWER}</body></html>"
    )
    return without_machine_paths(page, places or {})


class Figures:
    """Writes PNGs into RUN/report/ and returns the figure markup."""

    def __init__(self, folder: Path):
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)

    def image(
        self, name: str, rgb: torch.Tensor, caption: str, alpha: torch.Tensor | None = None, css: str = ""
    ) -> str:
        write_image(
            self.folder / f"{name}.png", rgb.detach().float().cpu().clamp_min(0), None if alpha is None else alpha.cpu()
        )
        return self.figure(name, caption, css)

    def figure(self, name: str, caption: str, css: str = "") -> str:
        """The markup of the picture `name` written before (shown again elsewhere on the page)."""
        return (
            f'<figure><img class="{css}" src="report/{name}.png" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )

    def scalar(self, name: str, values: torch.Tensor, caption: str, alpha: torch.Tensor | None = None) -> str:
        # scalar maps are shown as they are stored (linear values): undo the sRGB encoding of write_image
        return self.image(name, srgb_to_linear(values.clamp(0, 1))[..., None].expand(-1, -1, 3), caption, alpha)


def srgb_inverse(values: torch.Tensor) -> torch.Tensor:
    """Values meant to be shown as stored (normals as colours): pre-decode so write_image stores them."""
    return srgb_to_linear(values.clamp(0, 1))


def markdown_to_html(text: str) -> str:
    """The subset of markdown `tables.md` uses: headings, bullet lists, pipe tables, emphasis, code."""
    out, rows = [], []

    def flush_table():
        if rows:
            head, body = rows[0], [r for r in rows[2:]]
            out.append(
                "<table><tr>"
                + "".join(f"<th>{inline(c)}</th>" for c in head)
                + "</tr>"
                + "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>" for r in body)
                + "</table>"
            )
            rows.clear()

    for line in text.splitlines():
        if line.startswith("|"):
            rows.append(line.strip().strip("|").split("|"))
            continue
        flush_table()
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            out.append(f"<h{level + 1}>{inline(line.lstrip('#'))}</h{level + 1}>")
        elif line.startswith("- "):
            out.append(f"<p>• {inline(line[2:])}</p>")
        elif line.strip():
            out.append(f"<p>{inline(line)}</p>")
    flush_table()
    return "\n".join(out)


def inline(cell: str) -> str:
    """One cell or line of markdown: bold (**x**), a whole cell in italics (_x_), code (`x`)."""
    cell = html.escape(cell.strip())
    while cell.count("**") >= 2:
        cell = cell.replace("**", "<b>", 1).replace("**", "</b>", 1)
    while cell.count("`") >= 2:
        cell = cell.replace("`", "<code>", 1).replace("`", "</code>", 1)
    if cell.startswith("_") and cell.endswith("_") and len(cell) > 1:
        cell = f"<i>{cell[1:-1]}</i>"
    return cell
