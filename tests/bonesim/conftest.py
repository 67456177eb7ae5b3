"""Fixtures shared by the bonesim tests of several packages."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """8 s of the phantom's planned demo from its first drilling sample,
    recorded (the vision-dataset tests render it)."""
    from tests.bonesim.dataset_runs import demo_part, record

    return record(tmp_path_factory.mktemp("demo_run") / "demo.h5", demo_part(0.0, 8.0))
