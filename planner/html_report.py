"""Self-contained HTML reports beside every `report.json`.

`write_html_report` turns a (nested) JSON-like report dict into a single HTML page a surgeon
can open offline: scalar fields become a key/value table, a dict whose values are dicts of
scalars (e.g. `metrics.regions.<region>.<metric>`) becomes one table with a row per key, a
list of dicts (e.g. `effects`) becomes a table with a row per item, and the pictures are
embedded as base64 data URIs so the page needs no other file. Before/after pairs (pre-op and
predicted face from the same camera) are shown one over the other with a range slider that
uncovers the "after" picture from the left (inline CSS `clip-path` and a one-line inline
script; without script the slider is hidden and both pictures are shown side by side). The
page loads nothing from the network and reflows on a phone (viewport meta, pictures and tables
scale to the screen width). The raw JSON is appended in a collapsible block. Values are
HTML-escaped; floats are shown with a sensible precision.
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from planner.atomic import atomic_write_file

__all__ = ["write_html_report", "render_html_report", "table_html"]

_CSS = """
*{box-sizing:border-box}
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1100px;
color:#222;line-height:1.4;padding:0 .8em}
h1{font-size:1.6em;border-bottom:2px solid #4c72b0;padding-bottom:.2em}
h2{font-size:1.25em;margin-top:1.6em;color:#274b7a}h3{font-size:1.05em;margin-bottom:.3em}
table{border-collapse:collapse;margin:.5em 0 1em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#eef2f8}td.k,th.k{text-align:left}tr:nth-child(even) td{background:#fafafa}
figure{display:inline-block;margin:.4em;vertical-align:top;text-align:center;max-width:520px;width:100%}
figure img{max-width:100%;height:auto;border:1px solid #ddd}
.tbl{overflow-x:auto;max-width:100%}
.ba{display:inline-block;margin:.4em;vertical-align:top;width:100%;max-width:520px}
.ba .stack{position:relative;line-height:0;border:1px solid #ddd}
.ba .stack img{width:100%;height:auto;display:block}
.ba .stack img.after{position:absolute;top:0;left:0;clip-path:inset(0 0 0 50%)}
.ba input{width:100%;margin:.4em 0}
.ba .lbl{display:flex;justify-content:space-between;font-size:.85em;color:#555}
.nojs .ba .stack img.after{position:static;clip-path:none}.nojs .ba input{display:none}
@media (max-width:600px){body{margin:.5em auto;font-size:15px}h1{font-size:1.3em}
figure,.ba{margin:.3em 0;max-width:100%}th,td{padding:.2em .35em}}
figcaption{font-size:.85em;color:#555}
details{margin-top:2em}pre{background:#f6f6f6;padding:1em;overflow:auto;font-size:.8em}
.meta{color:#777;font-size:.85em}
"""


def _fmt(v: Any) -> str:
    if v is None:
        return "&ndash;"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if math.isnan(v):
            return "&ndash;"
        if v == 0 or 1e-3 <= abs(v) < 1e5:
            return f"{v:.3f}".rstrip("0").rstrip(".") if abs(v) < 100 else f"{v:.1f}"
        return f"{v:.3g}"
    if isinstance(v, (list, tuple)) and all(isinstance(x, (int, float)) for x in v) and len(v) <= 16:
        return "[" + ", ".join(_fmt(float(x)) if isinstance(x, float) else str(x) for x in v) + "]"
    if isinstance(v, (dict, list, tuple)):
        return html.escape(json.dumps(v, default=str))
    return html.escape(str(v))


def _is_scalar(v: Any) -> bool:
    return v is None or isinstance(v, (str, int, float, bool)) or (
        isinstance(v, (list, tuple)) and len(v) <= 16 and all(isinstance(x, (int, float)) for x in v))


def _title(key: str) -> str:
    return html.escape(str(key).replace("_", " "))


def table_html(columns: Sequence[str], rows: Iterable[Sequence[Any]], caption: str | None = None) -> str:
    """An HTML table; the first column is left-aligned (row names)."""
    out = ['<div class="tbl"><table>']
    if caption:
        out.append(f"<caption>{html.escape(caption)}</caption>")
    out.append("<tr>" + "".join(
        f'<th class="k">{html.escape(str(c))}</th>' if i == 0 else f"<th>{html.escape(str(c))}</th>"
        for i, c in enumerate(columns)) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(
            f'<td class="k">{_fmt(c)}</td>' if i == 0 else f"<td>{_fmt(c)}</td>"
            for i, c in enumerate(row)) + "</tr>")
    out.append("</table></div>")
    return "\n".join(out)


def _dict_of_records(d: Mapping) -> list[str] | None:
    """Column names if `d` maps keys to dicts of scalars (a table), else None."""
    if not d or not all(isinstance(v, Mapping) and v and all(_is_scalar(x) for x in v.values())
                        for v in d.values()):
        return None
    cols: list[str] = []
    for v in d.values():
        for k in v:
            if k not in cols:
                cols.append(k)
    return cols


def _section(key: str | None, value: Any, depth: int) -> list[str]:
    h = f"h{min(2 + depth, 4)}"
    out: list[str] = []
    if isinstance(value, Mapping):
        cols = _dict_of_records(value)
        if key is not None:
            out.append(f"<{h}>{_title(key)}</{h}>")
        if cols is not None:
            out.append(table_html([""] + cols, ([k] + [v.get(c) for c in cols] for k, v in value.items())))
            return out
        scalars = [(k, v) for k, v in value.items() if _is_scalar(v)]
        if scalars:
            out.append(table_html(["field", "value"], scalars))
        for k, v in value.items():
            if not _is_scalar(v):
                out.extend(_section(k, v, depth + 1))
        return out
    if isinstance(value, (list, tuple)):
        if key is not None:
            out.append(f"<{h}>{_title(key)}</{h}>")
        if value and all(isinstance(v, Mapping) for v in value):
            cols: list[str] = []
            for v in value:
                for k in v:
                    if k not in cols:
                        cols.append(k)
            out.append(table_html(cols, ([v.get(c) for c in cols] for v in value)))
        else:
            out.append("<ul>" + "".join(f"<li>{_fmt(v)}</li>" for v in value) + "</ul>")
        return out
    out.append(table_html(["field", "value"], [(key, value)]))
    return out


def _data_uri(path: Path) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    mime = {"png": "image/png", "jpg": "image/jpeg", "jpeg": "image/jpeg", "svg": "image/svg+xml",
            "gif": "image/gif"}.get(Path(path).suffix.lower().lstrip("."), "application/octet-stream")
    return f"data:{mime};base64,{data}"


def _image_html(path: Path, caption: str | None = None) -> str:
    cap = caption if caption is not None else Path(path).stem.replace("_", " ")
    return (f'<figure><img alt="{html.escape(cap)}" src="{_data_uri(path)}">'
            f"<figcaption>{html.escape(cap)}</figcaption></figure>")


# The slider uncovers the "after" picture: its clip rectangle starts at the slider's value.
_SLIDER_JS = ("this.parentNode.querySelector('img.after').style.clipPath="
              "'inset(0 0 0 '+this.value+'%)'")


def _before_after_html(caption: str, before: Path, after: Path,
                       labels: tuple[str, str] = ("pre-op", "predicted")) -> str:
    cap = html.escape(caption)
    return (f'<div class="ba"><div class="stack">'
            f'<img class="before" alt="{html.escape(labels[0])}, {cap}" src="{_data_uri(before)}">'
            f'<img class="after" alt="{html.escape(labels[1])}, {cap}" src="{_data_uri(after)}"></div>'
            f'<input type="range" min="0" max="100" value="50" aria-label="{cap}: {html.escape(labels[0])} '
            f'to {html.escape(labels[1])}" oninput="{_SLIDER_JS}">'
            f'<div class="lbl"><span>&larr; {html.escape(labels[0])}</span><span>{cap}</span>'
            f'<span>{html.escape(labels[1])} &rarr;</span></div></div>')


def render_html_report(
    title: str,
    report: Mapping[str, Any],
    images: Sequence[os.PathLike | str | tuple[os.PathLike | str, str]] = (),
    tables: Mapping[str, tuple[Sequence[str], Sequence[Sequence[Any]]]] | None = None,
    intro: str | None = None,
    before_after: Sequence[tuple[str, os.PathLike | str, os.PathLike | str]] = (),
    before_after_labels: tuple[str, str] = ("pre-op", "predicted"),
) -> str:
    """The HTML text (see `write_html_report`)."""
    parts = [
        "<!DOCTYPE html>", '<html lang="en" class="nojs"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title><style>{_CSS}</style>",
        "<script>document.documentElement.className='';</script></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="meta">generated {_dt.datetime.now().isoformat(timespec="seconds")} by faceplan</p>',
    ]
    if intro:
        parts.append(f"<p>{html.escape(intro)}</p>")
    if before_after:
        la, lb = (html.escape(x) for x in before_after_labels)
        heading = ("Before and after" if tuple(before_after_labels) == ("pre-op", "predicted")
                   else f"{la[:1].upper()}{la[1:]} and {lb}")
        parts.append(f"<h2>{heading}</h2><p class=\"meta\">Drag a slider: the {la} face left of it, "
                     f"the {lb} face right of it; the same camera for both.</p><div>")
        parts.extend(_before_after_html(c, Path(a), Path(b), tuple(before_after_labels))
                     for c, a, b in before_after)
        parts.append("</div>")
    for name, (columns, rows) in (tables or {}).items():
        parts.append(f"<h2>{html.escape(name)}</h2>")
        parts.append(table_html(columns, rows))
    if images:
        parts.append("<h2>Pictures</h2><div>")
        for item in images:
            if isinstance(item, tuple):
                parts.append(_image_html(Path(item[0]), item[1]))
            else:
                parts.append(_image_html(Path(item)))
        parts.append("</div>")
    scalars = [(k, v) for k, v in report.items() if _is_scalar(v)]
    if scalars:
        parts.append("<h2>Summary</h2>")
        parts.append(table_html(["field", "value"], scalars))
    for k, v in report.items():
        if not _is_scalar(v):
            parts.extend(_section(k, v, 0))
    parts.append("<details><summary>raw report.json</summary><pre>"
                 + html.escape(json.dumps(report, indent=2, default=str)) + "</pre></details>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_html_report(
    path: os.PathLike | str,
    title: str,
    report: Mapping[str, Any],
    images: Sequence[os.PathLike | str | tuple[os.PathLike | str, str]] = (),
    tables: Mapping[str, tuple[Sequence[str], Sequence[Sequence[Any]]]] | None = None,
    intro: str | None = None,
    before_after: Sequence[tuple[str, os.PathLike | str, os.PathLike | str]] = (),
    before_after_labels: tuple[str, str] = ("pre-op", "predicted"),
) -> Path:
    """Write a self-contained HTML page summarising `report` with `images` embedded.

    `images` are paths (caption from the file name) or (path, caption) pairs; `tables` are
    extra tables shown first, {heading: (column names, rows)}; `before_after`: (caption,
    pre-op picture, predicted picture) triples shown with a slider each (`before_after_labels`
    names the two pictures when they are other than pre-op and predicted).
    """
    text = render_html_report(title, report, images, tables, intro, before_after, before_after_labels)
    path = Path(path)
    with atomic_write_file(path, "w") as fh:
        fh.write(text)
    return path
