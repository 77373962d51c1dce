"""The documentation is true: its Python examples run, the scenario format page is current and complete, and every
public function, class and method says what it does."""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import re
import subprocess
import sys
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

import virtual_vehicle
from virtual_vehicle.config import scenario_doc

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").glob("*.md"))


def _blocks(page: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S)


def test_every_capability_page_has_a_runnable_example():
    pages = {p.name for p in PAGES}
    assert {"physics.md", "fields-and-equilibria.md", "distributed-control.md", "hardware.md", "data.md",
            "pictures.md", "rl.md", "scenario-format.md", "index.md"} <= pages
    for p in PAGES:
        if p.name not in ("index.md", "scenario-format.md"):
            assert _blocks(p), f"{p.name} has no Python example"
    index = (ROOT / "docs" / "index.md").read_text()
    assert all(p.name in index for p in PAGES if p.name != "index.md")


CONTINUES = "# continues the previous block"  # first line of a block that needs the one before it


def _scripts(page: Path) -> list[tuple[str, str]]:
    """The page's Python blocks as scripts: (id, code), a block marked with CONTINUES joined to the one before."""
    out: list[tuple[list[int], str]] = []
    for k, code in enumerate(_blocks(page)):
        if code.startswith(CONTINUES):
            assert out, f"{page.name} block {k} continues nothing"
            out[-1] = (out[-1][0] + [k], out[-1][1] + "\n" + code)
        else:
            out.append(([k], code))
    return [(f"{page.name}[{ks[0]}{f'-{ks[-1]}' if len(ks) > 1 else ''}]", code) for ks, code in out]


SCRIPTS = [(page, sid, code) for page in (ROOT / "README.md", *PAGES) for sid, code in _scripts(page)]


@pytest.fixture(scope="session")
def script_runs(request, tmp_path_factory):
    """The selected docs scripts, all started at once and run as many at a time as there are cores (4 at most),
    each in a fresh process of this interpreter (environment and PYTHONPATH unchanged, TMPDIR its own) in an empty
    working folder: (completed process, working folder) by script id, each waited for by its own test."""
    def launch(script, cwd, tmp):
        env = {**os.environ, "TMPDIR": str(tmp)}  # tempfile.mkdtemp() in an example lands here
        done = subprocess.run([sys.executable, str(script)], cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=1200)
        return done, cwd

    wanted = {item.callspec.params["sid"] for item in request.session.items
              if "sid" in getattr(getattr(item, "callspec", None), "params", {})}  # as selected (-k)
    jobs = {}
    for _, sid, code in SCRIPTS:
        if sid in wanted:
            root = tmp_path_factory.mktemp("docs")
            (root / "cwd").mkdir()
            (root / "tmp").mkdir()
            script = root / (re.sub(r"\W", "_", sid) + ".py")
            script.write_text(code)
            jobs[sid] = (script, root / "cwd", root / "tmp")
    with ThreadPoolExecutor(max_workers=max(1, min(4, os.cpu_count() or 1))) as pool:
        yield {sid: pool.submit(launch, *job) for sid, job in jobs.items()}


@pytest.mark.parametrize("sid", [sid for _, sid, _ in SCRIPTS])
def test_the_examples_run_as_scripts_and_write_nothing_where_they_run(sid, script_runs):
    """Each block runs as a script of its own in a fresh process (as a reader would run it: `__main__`, so that
    worker processes started by spawn import it again), alone unless it says it continues the previous block; and
    it writes its files into a temporary folder, none into the folder it runs in."""
    done, cwd = script_runs[sid].result()
    err = done.stderr if len(done.stderr) < 6000 else f"{done.stderr[:3000]}\n[...]\n{done.stderr[-3000:]}"
    assert done.returncode == 0, f"{sid} failed:\n{err}"
    assert sorted(p.name for p in cwd.iterdir()) == [], f"{sid} wrote into its working folder"


def test_the_scenario_format_page_is_current_and_names_every_field():
    page = (ROOT / "docs" / "scenario-format.md").read_text()
    assert page == scenario_doc.reference(), "regenerate: python -m virtual_vehicle.config.scenario_doc > docs/scenario-format.md"
    assert scenario_doc.undocumented() == []
    for _, model in scenario_doc.sections():
        for name in model.model_fields:
            assert f"| `{name}` |" in page


def _public():
    for m in pkgutil.walk_packages(virtual_vehicle.__path__, "virtual_vehicle."):
        mod = importlib.import_module(m.name)
        for name, obj in vars(mod).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != mod.__name__:
                continue
            if inspect.isfunction(obj) or inspect.isclass(obj):
                yield f"{m.name}.{name}", obj
                if inspect.isclass(obj):
                    for k, v in vars(obj).items():
                        if not k.startswith("_") and (inspect.isfunction(v) or isinstance(v, property)):
                            yield f"{m.name}.{name}.{k}", getattr(obj, k) if inspect.isfunction(v) else v


def test_every_public_function_class_and_method_has_a_docstring():
    missing = [name for name, obj in _public() if not inspect.getdoc(obj)]
    assert missing == []


def _default(model, key):
    """A field's default as TOML writes it (tuples as lists), or None when it has none or its default is none."""
    f = model.model_fields[key]
    if f.default is PydanticUndefined and f.default_factory is None:
        return None
    value = f.default_factory() if f.default_factory is not None else f.default

    def toml(v):
        return [toml(x) for x in v] if isinstance(v, (list, tuple)) else v

    return None if isinstance(value, BaseModel) else toml(value)


_LITERAL = r'(-?[0-9][0-9_.]*(?:e-?[0-9]+)?|"[^"]*"|true|false)(?![\w\[."])'


def _readme_defaults() -> list[tuple[str, str, object, object]]:
    """(where, key, value in the README, model default) for every value the README's TOML block states as a
    default: each ``key = value`` line (commented out or not) of a field that has a default, unless its comment
    starts with "e.g." (an example), and each ``key = literal`` inside a comment that names a field of the table
    it is in. Fails on a key its table does not have."""
    models = {}
    for label, model in scenario_doc.sections():
        label = re.sub(r'\] kind = "\w+"\.', ".", label)  # '[[array] kind = "grid".belts]]': [[array.belts]]
        m = re.fullmatch(r'\[\[?([\w.]+)\]\]?(?: (?:kind|program) = "(\w+)")?', label)
        models[(m.group(1), m.group(2)) if label != "(top level)" else ("", None)] = model
    block = re.search(r"```toml\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S).group(1)
    section, kind, found = "", None, []

    def model_here(key=None):
        """The table's model for its kind (or program), else one of the table's models that has ``key``."""
        here = models.get((section, kind)) or models.get((section, None))
        if here is not None and (key is None or key in here.model_fields):
            return here
        return next((m for (s, _), m in models.items() if s == section and key in m.model_fields), here)

    for line in block.splitlines():
        body = line[1:].strip() if line.startswith("#") else line.strip()
        head = re.match(r"\[\[?([\w.]+)\]\]?(\s{2,}|\s*#|\s*$)", body)  # "[table]", then 2 spaces or a comment
        if head:
            section, kind = head.group(1), None
            comment = body[head.end():]
        else:
            try:
                (key, value), = tomllib.loads(body).items()
            except (tomllib.TOMLDecodeError, ValueError):
                comment = body  # prose
            else:
                comment = body.split("#", 1)[1] if "#" in body else ""
                if key in ("kind", "program"):
                    kind = value
                    continue
                model = model_here(key)
                assert model is not None and key in model.model_fields, f"README: no field {key!r} in [{section}]"
                if not comment.strip().startswith("e.g.") and _default(model, key) is not None:
                    found.append((f"[{section}]", key, value, _default(model, key)))
        for key, literal in re.findall(r"\b(\w+) = " + _LITERAL, comment):
            model = model_here(key)
            if model is not None and key in model.model_fields and key != "kind" and _default(model, key) is not None:
                found.append((f"[{section}] (comment)", key, tomllib.loads(f"v = {literal}")["v"],
                              _default(model, key)))
    return found


def test_the_defaults_the_readme_states_are_the_models():
    stated = _readme_defaults()
    keys = {key for _, key, _, _ in stated}
    assert len(stated) >= 30 and {"hop_limit", "heartbeat", "delivery", "gap", "reach", "baud"} <= keys
    wrong = [f"{where} {key} = {value!r}, default {default!r}" for where, key, value, default in stated
             if value != default]
    assert wrong == []


def _format_page_defaults() -> list[tuple[str, str, object, object]]:
    """(section, key, stated, model default) for the defaults the scenario format page states in its prose:
    "`key` (..., default V)", "`key = V` (..., default)" and "`key`: `V` (..., default)" with V a TOML literal."""
    page = (ROOT / "docs" / "scenario-format.md").read_text()
    models = {model.__name__: model for _, model in scenario_doc.sections()}
    found = []
    for title, text in re.findall(r"^## `[^`]*` \((\w+)\)\n(.*?)(?=^## |\Z)", page, flags=re.S | re.M):
        model = models[title]
        prose = " ".join(line for line in text.splitlines() if not line.startswith("|"))
        pairs = re.findall(r"`(\w+)` \([^()]*?\bdefault " + _LITERAL + r"\)", prose)
        pairs += re.findall(r"`(\w+) = " + _LITERAL + r"` \([^()]*\bdefault\)", prose)
        pairs += re.findall(r"`(\w+)`: `" + _LITERAL + r"` \([^()]*\bdefault\)", prose)
        for key, literal in pairs:
            assert key in model.model_fields, f"scenario-format.md: no field {key!r} in {title}"
            found.append((title, key, tomllib.loads(f"v = {literal}")["v"], _default(model, key)))
    return found


def test_the_defaults_the_format_page_states_in_words_are_the_models():
    stated = _format_page_defaults()
    assert {key for _, key, _, _ in stated} >= {"changed_only", "batch", "wheels", "mode"}
    assert [s for s in stated if s[2] != s[3]] == []
