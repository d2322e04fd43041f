"""One report, two files: ``report.md`` (images linked) and a self-contained ``report.html``
(images inlined as base64 PNG), built from the same blocks so they never disagree."""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path

from facesynth.io import write_text

_CSS = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:2px 8px;text-align:right}"
        "td:first-child,th:first-child{text-align:left}img{max-width:100%}figcaption{color:#444;font-size:90%}"
        "ul.verdict{padding-left:1.2em;margin:0.3em 0}ul.verdict li{margin:0.15em 0}"
        "details{margin:0.4em 0;border-top:1px solid #ddd}summary{cursor:pointer;font-weight:bold;padding:0.3em 0}")


class Document:
    """Blocks of a report: headings, paragraphs, bullet lists, tables, figures and collapsible
    sections (``<details>`` in HTML, a heading in Markdown)."""

    def __init__(self, title: str):
        self.title = title
        self.blocks: list[tuple] = []

    def heading(self, text: str, level: int = 2) -> None:
        self.blocks.append(("h", level, text))

    def para(self, text: str) -> None:
        self.blocks.append(("p", text))

    def bullets(self, items: list[str], css_class: str = "") -> None:
        self.blocks.append(("ul", list(items), css_class))

    def open_section(self, summary: str) -> None:
        """Start a collapsible section (closed by :meth:`close_section`), collapsed in HTML."""
        self.blocks.append(("details", summary))

    def close_section(self) -> None:
        self.blocks.append(("/details",))

    def table(self, header: list[str], rows: list[list]) -> None:
        self.blocks.append(("table", list(header), [list(map(str, r)) for r in rows]))

    def figure(self, path: str, caption: str) -> None:
        """``path`` relative to the report's folder."""
        self.blocks.append(("img", path, caption))

    @property
    def images(self) -> list[str]:
        return [b[1] for b in self.blocks if b[0] == "img"]

    def markdown(self) -> str:
        out = [f"# {self.title}", ""]
        for b in self.blocks:
            if b[0] == "h":
                out += ["#" * b[1] + " " + b[2], ""]
            elif b[0] == "p":
                out += [b[1], ""]
            elif b[0] == "ul":
                out += [f"- {t}" for t in b[1]] + [""]
            elif b[0] == "details":
                out += [f"## {b[1]}", ""]
            elif b[0] == "/details":
                continue
            elif b[0] == "table":
                out += ["| " + " | ".join(b[1]) + " |", "|---" + "|---:" * (len(b[1]) - 1) + "|"]
                out += ["| " + " | ".join(r) + " |" for r in b[2]] + [""]
            else:
                out += [f"![{b[2]}]({b[1]})", "", f"*{b[2]}*", ""]
        return "\n".join(out)

    def html(self, base: str | os.PathLike) -> str:
        """Self-contained HTML; figures are read from ``base / path`` and inlined."""
        e = html.escape
        out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(self.title)}</title>"
               f"<style>{_CSS}</style></head><body><h1>{e(self.title)}</h1>"]
        for b in self.blocks:
            if b[0] == "h":
                out.append(f"<h{b[1]}>{e(b[2])}</h{b[1]}>")
            elif b[0] == "p":
                out.append(f"<p>{e(b[1])}</p>")
            elif b[0] == "ul":
                cls = f" class='{e(b[2])}'" if b[2] else ""
                out.append(f"<ul{cls}>" + "".join(f"<li>{e(t)}</li>" for t in b[1]) + "</ul>")
            elif b[0] == "details":
                out.append(f"<details><summary>{e(b[1])}</summary>")
            elif b[0] == "/details":
                out.append("</details>")
            elif b[0] == "table":
                head = "".join(f"<th>{e(h)}</th>" for h in b[1])
                body = "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in b[2])
                out.append(f"<table><tr>{head}</tr>{body}</table>")
            else:
                data = base64.b64encode((Path(base) / b[1]).read_bytes()).decode("ascii")
                out.append(f"<figure><img alt='{e(b[1])}' src='data:image/png;base64,{data}'>"
                           f"<figcaption>{e(b[2])}</figcaption></figure>")
        return "\n".join(out + ["</body></html>"]) + "\n"

    def write(self, out_dir: str | os.PathLike, stem: str = "report") -> tuple[Path, Path]:
        """Write ``stem.md`` and ``stem.html`` into ``out_dir``."""
        d = Path(out_dir)
        write_text(d / f"{stem}.md", self.markdown())
        write_text(d / f"{stem}.html", self.html(d))
        return d / f"{stem}.md", d / f"{stem}.html"
