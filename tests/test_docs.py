"""The documentation is true: its Python examples run, the scenario format page is current and complete, and every
public function, class and method says what it does."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

import virtual_vehicle
from virtual_vehicle import scenario_doc

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


@pytest.mark.parametrize("page", [p for p in PAGES if _blocks(p)], ids=lambda p: p.name)
def test_the_examples_on_a_page_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # examples that write files write them here
    namespace: dict = {"__name__": "__docs__"}
    for k, code in enumerate(_blocks(page)):
        exec(compile(code, f"{page.name}[block {k}]", "exec"), namespace)


def test_the_scenario_format_page_is_current_and_names_every_field():
    page = (ROOT / "docs" / "scenario-format.md").read_text()
    assert page == scenario_doc.reference(), "regenerate: python -m virtual_vehicle.scenario_doc > docs/scenario-format.md"
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
