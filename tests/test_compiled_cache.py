"""The compiled code's cache folder is named by the sources compiled code can reach, so that an edit of a kernel
another kernel calls compiles the caller afresh (numba's own cache checks only the caller's file)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from virtual_vehicle import compiled_cache

CALLEE = "import numba\n\n@numba.njit(cache=True)\ndef g():\n    return {value}\n"
CALLER = textwrap.dedent("""
    import numba
    from pkg.engine.callee import g

    @numba.njit(cache=True)
    def f():
        return g()
""")


def _tree(root: Path, value: int) -> None:
    (root / "engine").mkdir(parents=True, exist_ok=True)
    (root / "ui").mkdir(exist_ok=True)
    for folder in (root, root / "engine", root / "ui"):
        (folder / "__init__.py").touch()
    (root / "engine" / "callee.py").write_text(CALLEE.format(value=value))
    (root / "engine" / "caller.py").write_text(CALLER)


def _run(base: Path, cache: Path | None) -> int:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_CACHE_DIR", compiled_cache._OURS))}
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    out = subprocess.run([sys.executable, "-c", "from pkg.engine.caller import f; print(f())"], cwd=base, env=env,
                         capture_output=True, text=True, check=True)
    return int(out.stdout.strip())


def test_an_edited_callee_is_compiled_afresh_into_its_callers(tmp_path):
    """After the callee's file alone changed, numba's default cache (numba 0.6x) runs the caller compiled against
    the callee's old body; the folder named by the sources runs the new one."""
    root = tmp_path / "pkg"
    _tree(root, 1)
    assert _run(tmp_path, None) == 1
    assert _run(tmp_path, compiled_cache.cache_folder(root)) == 1
    (root / "engine" / "callee.py").write_text(CALLEE.format(value=2))
    assert _run(tmp_path, compiled_cache.cache_folder(root)) == 2


def test_the_hash_follows_the_compiled_layers_only(tmp_path):
    root = tmp_path / "pkg"
    _tree(root, 1)
    first = compiled_cache.source_hash(root)
    (root / "ui" / "view.py").write_text("x = 1\n")
    assert compiled_cache.source_hash(root) == first
    (root / "engine" / "callee.py").write_text(CALLEE.format(value=1) + "# a comment\n")
    assert compiled_cache.source_hash(root) != first
    (root / "engine" / "callee.py").write_text(CALLEE.format(value=1))
    assert compiled_cache.source_hash(root) == first


def test_stale_folders_of_other_sources_are_removed(tmp_path):
    root = tmp_path / "pkg"
    _tree(root, 1)
    old, recent = root / "__pycache__" / "numba-0000", root / "__pycache__" / "numba-1111"
    old.mkdir(parents=True)
    recent.mkdir()
    os.utime(old, (1.0, 1.0))
    folder = compiled_cache.cache_folder(root)
    assert folder.is_dir() and folder.name == f"numba-{compiled_cache.source_hash(root)}"
    assert not old.exists() and recent.exists()


def test_the_callers_choice_wins_and_ours_is_chosen_again(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    monkeypatch.delenv(compiled_cache._OURS, raising=False)
    assert compiled_cache.choose() is None
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")
    monkeypatch.setenv(compiled_cache._OURS, str(tmp_path / "mine"))  # as a parent process of ours left it
    folder = compiled_cache.choose()
    assert folder is not None and os.environ["NUMBA_CACHE_DIR"] == str(folder)
    assert folder.name == f"numba-{compiled_cache.source_hash()}"
