"""Shared test helpers: paths to the bundled fixtures and to ../shared/realbags."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"
# The real recordings are maintained outside the project, beside the checkout.
REALBAGS = Path(os.environ.get("PERFROS_REALBAGS", ROOT.parent / "shared" / "realbags"))


@pytest.fixture
def realbags() -> Path:
    if not REALBAGS.is_dir():
        raise RuntimeError(f"real recordings not found at {REALBAGS} (set PERFROS_REALBAGS)")
    return REALBAGS
