"""The Python examples of the README, as the tests run them: a user copies these blocks
first, so a renamed function or field must fail a test, not the user."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def python_blocks() -> list[str]:
    """The README's ```python blocks, in order."""
    return re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S)


def block_using(name: str) -> str:
    """The one README block that imports `name` (a module path)."""
    found = [b for b in python_blocks() if f"from {name} import" in b]
    assert len(found) == 1, f"expected one README block importing from {name}, found {len(found)}"
    return found[0]
