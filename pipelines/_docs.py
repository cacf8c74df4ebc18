"""The one way a pipeline writes its results into a docs page: between two markers."""

from __future__ import annotations

import shutil
from pathlib import Path

from perfros_bag.fileio import atomic_write_text


def write_section(docs: Path, name: str, section: str, out: Path, images: tuple[str, ...], title: str) -> None:
    """Replace what stands between ``<!-- NAME-results:begin -->`` and ``...:end -->`` in
    ``docs`` with ``section`` (the markers are appended, or the page made with ``title``,
    when missing); copy ``images`` that exist in ``out`` into ``docs``'s folder ``NAME/``."""
    begin, end = f"<!-- {name}-results:begin -->", f"<!-- {name}-results:end -->"
    text = docs.read_text() if docs.exists() else f"# {title}\n\n{begin}\n{end}\n"
    if begin not in text:
        text += f"\n{begin}\n{end}\n"
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    atomic_write_text(docs, f"{head}{begin}\n{section}\n{end}{tail}")
    img = docs.parent / name
    img.mkdir(exist_ok=True)
    for image in images:
        if (out / image).exists():
            shutil.copyfile(out / image, img / image)
