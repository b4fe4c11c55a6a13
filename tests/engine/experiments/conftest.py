"""The experiments run on the localization tests' small lab and its database."""

from tests.engine.localization.conftest import lab, lab_db, make_lab, rng  # noqa: F401
