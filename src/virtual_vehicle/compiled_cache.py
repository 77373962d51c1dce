"""Where numba keeps the package's compiled code: a folder named by the sources it was compiled from.

numba's own cache checks only the file a compiled function is written in. A kernel compiled into another
(``engine/_modeloop`` calling ``engine/_kernel``, which calls ``physics/contact``) and the module constants it
reads are frozen into the caller's cached code, so after an edit of ``contact.py`` alone the cached loop went on
running the old support solve, silently. Here the cache folder is named by a hash of every source a compiled
function can reach: by the layer rule (imports only go downward, ``docs/architecture.md``) the compiled code lives
in ``model/``, ``physics/``, ``engine/`` and ``cells/`` and can read only those and the package's root modules. An
edit there compiles afresh (about a minute); an edit above (``config/``, ``run/``, ``analysis/``, ``ui/``) does not.

The folder is ``src/virtual_vehicle/__pycache__/numba-HASH`` (beside the sources, as numba's default), or, where
that cannot be written (an installed package), ``$XDG_CACHE_HOME/virtual_vehicle/numba-HASH`` (default
``~/.cache``). Folders of other hashes untouched for a day are removed. ``NUMBA_CACHE_DIR``, when the caller set it,
wins: then numba's own check is all there is.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
COMPILED_LAYERS = ("model", "physics", "engine", "cells")
"""The subpackages whose sources name the cache (with the root modules): those compiled code can reach."""
STALE_S = 86400.0
"""Folders of other source hashes not modified for this long (s) are removed when the cache is chosen."""


def source_hash(root: Path = ROOT) -> str:
    """A 16-hex-digit hash of the ``.py`` sources compiled code can reach: the root modules and the
    :data:`COMPILED_LAYERS` subpackages of ``root``, each named by its path relative to ``root``."""
    files = sorted(root.glob("*.py")) + sorted(p for layer in COMPILED_LAYERS for p in (root / layer).rglob("*.py"))
    digest = hashlib.blake2b(digest_size=8)
    for path in files:
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _prune(parent: Path, keep: Path, now: float) -> None:
    for other in parent.glob("numba-*"):
        try:
            if other != keep and other.is_dir() and now - other.stat().st_mtime > STALE_S:
                shutil.rmtree(other, ignore_errors=True)
        except OSError:  # gone meanwhile (another process pruned it)
            pass


def cache_folder(root: Path = ROOT) -> Path | None:
    """The folder for the compiled code of the sources under ``root`` (made, writable), or None when neither place
    can be written (numba then caches where it can, by its own check). Prunes stale sibling folders."""
    name = f"numba-{source_hash(root)}"
    user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "virtual_vehicle"
    for parent in (root / "__pycache__", user):
        folder = parent / name
        if _writable(folder):
            _prune(parent, folder, time.time())
            return folder
    return None


_OURS = "VIRTUAL_VEHICLE_NUMBA_CACHE_DIR"
"""Set beside ``NUMBA_CACHE_DIR`` when this module chose it, so that a child process (a sweep's worker, another
checkout run from this one) chooses again for its own sources instead of taking the parent's folder as the user's."""


def choose() -> Path | None:
    """Point numba's cache at :func:`cache_folder` unless the caller set ``NUMBA_CACHE_DIR``; called by the package's
    ``__init__``, before any compiled function of the package is defined. numba reads ``NUMBA_CACHE_DIR`` when it is
    imported (set here, so that importing the package does not import numba); if it already is, its config is set
    too. Returns the folder used, or None."""
    given = os.environ.get("NUMBA_CACHE_DIR")
    if given and os.environ.get(_OURS) != given:
        return None
    folder = cache_folder()
    if folder is None:
        return None
    os.environ["NUMBA_CACHE_DIR"] = os.environ[_OURS] = str(folder)
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.CACHE_DIR = str(folder)
    return folder
