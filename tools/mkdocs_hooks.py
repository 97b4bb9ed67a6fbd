"""mkdocs hook (``hooks:`` in mkdocs.yml): regenerate the docs' generated snippets before each build,
so the CLI reference and every results table come from the parsers and the JSON of this checkout."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from tools import docgen  # noqa: E402

GENERATED = ROOT / "docs" / "_generated"


def on_pre_build(config: Any) -> None:
    docgen.write_all(GENERATED)
