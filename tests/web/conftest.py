"""The daemon tests' fixtures (a short socket directory, the laser twin) for the web tests."""

from tests.daemon.conftest import short_dir

__all__ = ["short_dir"]
