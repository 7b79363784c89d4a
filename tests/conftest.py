"""Shared fixtures: one headless GL context and the built-in scene, made once per test session."""
import pytest


@pytest.fixture(scope="session")
def ctx():
    from quadcast.render.gl import gl_context
    return gl_context()


@pytest.fixture(scope="session")
def courtyard():
    from quadcast.render.scene import load_scene
    return load_scene("builtin:courtyard")


@pytest.fixture(scope="session")
def courtyard_renderer(ctx, courtyard):
    from quadcast.render.renderer import DeferredRenderer
    return DeferredRenderer(courtyard, ctx)
