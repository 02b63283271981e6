"""MkDocs hook: the generated ``results/`` folder joins the site as it is, so the docs link to
``results/<file>.md`` and the strict build checks those links, without a copy in ``docs/``."""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File, Files

RESULTS = Path(__file__).resolve().parents[1] / "results"


def on_files(files: Files, *, config) -> Files:  # noqa: ANN001 - MkDocs' hook signature
    for path in sorted(RESULTS.rglob("*")):
        if path.is_file():
            uri = "results/" + path.relative_to(RESULTS).as_posix()
            files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


def on_page_markdown(markdown: str, *, page, config, files) -> str:  # noqa: ANN001 - MkDocs' hook signature
    # the generated tables write intervals side by side ("[a, b] [c]"), which Markdown would
    # read as reference links; shown literally instead
    if page.file.src_uri.startswith("results/"):
        return re.sub(r"\]( ?)\[", r"]\1\\[", markdown)
    return markdown
