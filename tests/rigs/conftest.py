"""Fixtures shared by the rig tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def headless_gl() -> None:
    """Skip, with the reason, where the raster backend cannot run: it needs pyrender, PyOpenGL and a
    headless EGL context. Probed once by opening and closing a GL context, so a machine without
    them skips while a render that fails where GL works is a failure, not a skip."""
    pytest.importorskip("pyrender", reason="pyrender not installed")
    pytest.importorskip("OpenGL", reason="PyOpenGL not installed")
    from omnigen.scenes.gl_raster import GLRaster

    try:
        GLRaster().close()
    except Exception as exc:  # no headless GL here
        pytest.skip(f"headless EGL rendering unavailable: {exc}")
