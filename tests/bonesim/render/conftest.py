"""Fixtures for the rendering tests: offscreen GL (EGL/OSMesa, no display,
no GPU needed), the phantom model, a small block model with a nerve."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def gl_info():
    """The offscreen OpenGL path (fails with the reason if there is none)."""
    from bonesim.render.gl import select_backend

    return select_backend(offscreen=True)


@pytest.fixture(scope="session")
def phantom(gl_info):
    from bonesim.io.loading import load_model

    return load_model("phantom", "cutting-5mm")


@pytest.fixture
def block():
    """(model, state) of :func:`tests.bonesim.render.scenes.nerve_block`."""
    from tests.bonesim.render.scenes import nerve_block

    return nerve_block()
