"""Shared pieces of the path-tracer tests: one GL context for the session."""
import pytest

from torchmanifold.render import create_context


@pytest.fixture(scope="session")
def ctx():
    c = create_context()
    assert c.error == "GL_NO_ERROR"
    yield c
    assert c.error == "GL_NO_ERROR"
