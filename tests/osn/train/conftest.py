"""The ``tiny`` dataset's exact valid region, as ``osn train`` hands it to training."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenecore.dataset import load_valid_region
from scenecore.validity import ValidRegion


@pytest.fixture(scope="session")
def tiny_region(tiny_dataset: Path) -> ValidRegion:
    return load_valid_region(tiny_dataset)
