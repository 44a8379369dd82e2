"""Write one API page per public name of o3dreg, and the API index.

Run after adding a public name: ``python docs/gen_api.py``. ``tests/test_docs.py`` fails when the
pages and ``o3dreg.__all__`` disagree.
"""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import o3dreg

#: Topic of each module, in the order the index lists them.
TOPICS = {
    "elastic": "Registration",
    "rigid": "Registration",
    "options": "Registration",
    "terms": "Registration: terms, losses, checkers",
    "losses": "Registration: terms, losses, checkers",
    "checkers": "Registration: terms, losses, checkers",
    "landmark_start": "Registration",
    "result": "Registration",
    "deformation": "Deformation of space",
    "lattice": "Deformation of space",
    "volume": "CT volumes and meshes",
    "readers": "CT volumes and meshes",
    "raw_slices": "CT volumes and meshes",
    "isosurface": "CT volumes and meshes",
    "cleaning": "CT volumes and meshes",
    "mesh": "CT volumes and meshes",
    "batch": "Shape models",
    "settings": "Shape models",
    "procrustes": "Shape models",
    "build": "Shape models",
    "model": "Shape models",
    "fit": "Shape models",
    "landmark_transfer": "Shape models",
    "landmark_files": "Shape models",
    "quality": "Shape models",
    "sliding": "Shape models",
    "statismo": "Shape models",
    "render": "Pictures",
}

HERE = Path(__file__).resolve().parent


def public_names() -> list[str]:
    return sorted(n for n in o3dreg.__all__ if not n.startswith("_"))


def topic(name: str) -> str:
    module = inspect.getmodule(getattr(o3dreg, name))
    short = module.__name__.rsplit(".", 1)[-1] if module else ""
    return TOPICS.get(short, "Other")


def summary(name: str) -> str:
    """The first paragraph of the docstring of ``name``, on one line (a summary that a docstring
    wraps over several lines stays whole)."""
    doc = inspect.getdoc(getattr(o3dreg, name)) or ""
    paragraph = doc.strip().split("\n\n")[0]
    line = " ".join(part.strip() for part in paragraph.splitlines())
    # Sphinx roles read badly in a Markdown table: keep the name only.
    line = re.sub(r":\w+:`~?(?:o3dreg\.)?([^`]+)`", r"`\1`", line)
    return line.replace("``", "`").replace("|", "\\|")


def render() -> dict[str, str]:
    """Path (relative to docs/api) -> content of every generated page."""
    pages = {}
    groups: dict[str, list[str]] = {}
    for name in public_names():
        pages[f"{name}.md"] = f"# o3dreg.{name}\n\n::: o3dreg.{name}\n"
        groups.setdefault(topic(name), []).append(name)
    order = list(dict.fromkeys([*TOPICS.values(), "Other"]))
    lines = ["# API reference", "", "Every public name of `o3dreg`, one page each.", ""]
    for group in order:
        if group not in groups:
            continue
        lines += [f"## {group}", "", "| name | summary |", "|---|---|"]
        for name in groups[group]:
            lines.append(f"| [`{name}`]({name}.md) | {summary(name)} |")
        lines.append("")
    pages["index.md"] = "\n".join(lines)
    return pages


def main() -> None:
    out = HERE / "api"
    out.mkdir(exist_ok=True)
    pages = render()
    for old in out.glob("*.md"):
        if old.name not in pages:
            old.unlink()
    for name, text in pages.items():
        (out / name).write_text(text, encoding="utf-8")
    print(f"wrote {len(pages)} pages to {out}")


if __name__ == "__main__":
    main()
