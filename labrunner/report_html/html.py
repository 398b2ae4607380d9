"""HTML pieces of the report: escaping, tables, inlined images, and the small Markdown subset the
fit's summary uses. Everything is inline (no CDN, no external request) so the file opens offline."""

from __future__ import annotations

import base64
import html
import io
import re
from collections.abc import Iterable, Sequence

from matplotlib.figure import Figure

STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1180px;
 padding:0 24px 48px;color:#1d232a;line-height:1.45}
h1{font-size:28px;margin:24px 0 4px}h2{font-size:21px;margin:34px 0 8px;border-bottom:2px solid #d7dde3;
 padding-bottom:4px}h3{font-size:16px;margin:22px 0 6px}
.sub{color:#5a6570;margin:0 0 14px}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:12px 0}
.card{background:#f3f6f9;border:1px solid #d7dde3;border-radius:8px;padding:8px 14px;min-width:120px}
.card b{display:block;font-size:20px}.card span{color:#5a6570;font-size:13px}
.status-done b{color:#1a7f37}.status-paused b,.status-aborted b{color:#b35900}.status-failed b{color:#c62828}
.status-running b{color:#1f5fb4}
.gain{font-size:16px;margin:6px 0}
.note{background:#fff8e1;border-left:4px solid #f0b400;padding:6px 12px;margin:8px 0}
table{border-collapse:collapse;font-size:13px;margin:6px 0 12px}
th,td{border:1px solid #d7dde3;padding:3px 7px;text-align:left;vertical-align:top}
th{background:#eef2f6;position:sticky;top:0}tr:nth-child(even) td{background:#fafbfc}
.scroll{max-height:420px;overflow:auto;border:1px solid #d7dde3;display:inline-block;max-width:100%}
.scroll table{margin:0}
input.filter{font-size:14px;padding:4px 8px;width:340px;margin:4px 0}
img.fig{max-width:100%;height:auto;display:block;margin:6px 0 2px;border:1px solid #e4e8ec}
.caption{color:#5a6570;font-size:13px;margin:0 0 16px}
code{background:#f3f6f9;padding:0 3px;border-radius:3px}
nav a{margin-right:12px}
"""

# Rows of a table whose id the input names are hidden unless their text contains what is typed.
FILTER_JS = """
function lrFilter(input){var q=input.value.toLowerCase();
 var rows=document.getElementById(input.dataset.table).tBodies[0].rows;var shown=0;
 for(var i=0;i<rows.length;i++){var ok=rows[i].textContent.toLowerCase().indexOf(q)>=0;
  rows[i].style.display=ok?"":"none";if(ok)shown++;}
 document.getElementById(input.dataset.table+"-count").textContent=shown+" of "+rows.length+" rows";}
"""


def esc(text: object) -> str:
    return html.escape(str(text), quote=True)


def png_data_uri(fig: Figure, dpi: int = 80) -> str:
    """A figure as a base64 PNG data URI (inlined: the report must open offline)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def image(uri: str, alt: str, caption: str, fig_id: str) -> str:
    return (f'<img class="fig" id="{esc(fig_id)}" src="{uri}" alt="{esc(alt)}">'
            f'<p class="caption">{esc(caption)}</p>')


def table(header: Sequence[str], rows: Iterable[Sequence[object]], table_id: str | None = None) -> str:
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in rows)
    ident = f' id="{esc(table_id)}"' if table_id else ""
    return f"<table{ident}><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def filterable_table(header: Sequence[str], rows: Sequence[Sequence[object]], table_id: str, hint: str) -> str:
    """A scrollable table with a text filter above it (FILTER_JS)."""
    return (f'<input class="filter" type="search" placeholder="{esc(hint)}" data-table="{esc(table_id)}" '
            f'oninput="lrFilter(this)"> <span id="{esc(table_id)}-count">{len(rows)} rows</span>'
            f'<div class="scroll">{table(header, rows, table_id)}</div>')


def note(text: str) -> str:
    return f'<p class="note">{esc(text)}</p>'


_INLINE = [(re.compile(r"\*\*(.+?)\*\*"), r"<b>\1</b>"), (re.compile(r"`([^`]+)`"), r"<code>\1</code>")]


def _inline(text: str) -> str:
    out = esc(text)
    for pattern, repl in _INLINE:
        out = pattern.sub(repl, out)
    return out


def markdown(text: str, heading_offset: int = 2) -> str:
    """The Markdown the fit's summary is written in — headings, pipe tables, lists, paragraphs, bold,
    code — as HTML. Not a general Markdown renderer: the summary is ours, and a dependency for it
    would be one more thing to install on a lab PC."""
    out: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].rstrip()
        if not line:
            i += 1
        elif line.startswith("#"):
            level = min(6, len(line) - len(line.lstrip("#")) + heading_offset)
            out.append(f"<h{level}>{_inline(line.lstrip('#').strip())}</h{level}>")
            i += 1
        elif line.startswith("|"):
            block = []
            while i < len(lines) and lines[i].startswith("|"):
                block.append([c.strip() for c in lines[i].strip().strip("|").split("|")])
                i += 1
            body = [r for r in block[1:] if not all(set(c) <= set("-: ") for c in r)]
            out.append("<table><thead><tr>" + "".join(f"<th>{_inline(c)}</th>" for c in block[0]) + "</tr></thead>"
                       "<tbody>" + "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>"
                                           for r in body) + "</tbody></table>")
        elif line.startswith("- "):
            items = []
            while i < len(lines) and lines[i].startswith("- "):
                items.append(f"<li>{_inline(lines[i][2:])}</li>")
                i += 1
            out.append("<ul>" + "".join(items) + "</ul>")
        else:
            para = []
            while i < len(lines) and lines[i].strip() and not lines[i].startswith(("#", "|", "- ")):
                para.append(lines[i].strip())
                i += 1
            out.append(f"<p>{_inline(' '.join(para))}</p>")
    return "\n".join(out)
