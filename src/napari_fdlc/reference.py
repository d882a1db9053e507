"""Built-in reference panel (placeholder until the atlas is built)."""
from __future__ import annotations

from .errors import ModelError


def load_panel():
    raise ModelError("the built-in reference panel is not built yet: pass --template")
