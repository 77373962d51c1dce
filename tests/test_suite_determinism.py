"""The suite is deterministic: every run draws the same hypothesis examples on any machine and keeps no example
database (the "ci" profile loaded in conftest.py), so a green run stays green on a fresh clone."""

from hypothesis import given, settings
from hypothesis import strategies as st


def test_every_run_draws_the_same_examples_and_keeps_no_database():
    assert settings.default.database is None and settings.default.derandomize
    runs: list[list] = [[], []]
    for drawn in runs:
        @settings(max_examples=25)  # inherits the loaded profile, as every test's @settings does
        @given(st.integers(0, 10_000), st.floats(0.0, 1.0))
        def draw(seed, frac):
            drawn.append((seed, frac))

        draw()
    assert runs[0] == runs[1] and len(set(runs[0])) > 1
