"""The scenario file format's reference, generated from the validating models themselves so it cannot drift:
every table, every field with its type, default and limits, and the model's own description (units in SI).

``python -m virtual_vehicle.config.scenario_doc > docs/scenario-format.md`` rewrites the page (a test checks it is
current).
"""

from __future__ import annotations

import inspect
import re
import textwrap
import types
import typing
from collections.abc import Iterator

import annotated_types as at
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from virtual_vehicle.config import scenario as S

INTRO = """# Scenario file format

A scenario is a TOML file (or a bundled name: `virtual-vehicle scenarios`). Every value is checked when it is
loaded; a bad one gives one message naming the field and exit code 2. Units are SI throughout: m, s, kg,
kg m^2, rad, m/s, rad/s, m/s^2, N, V, ohm. A scenario built in Python (`virtual_vehicle.config.scenario.Scenario`)
takes the same fields as keyword arguments.

This page is generated from the models that validate the files (`python -m virtual_vehicle.config.scenario_doc`);
*required* marks a field without a default. A table chosen by `kind` (the array, the field) takes the fields of
the section for that kind; the `[control]` table, chosen by `program`, those of the section for that program.
"""


def _models(t) -> list[type[BaseModel]]:
    """The pydantic models inside a type annotation."""
    if isinstance(t, type) and issubclass(t, BaseModel):
        return [t]
    return [m for a in typing.get_args(t) for m in _models(a)]


def _type_name(t) -> str:
    origin = typing.get_origin(t)
    args = typing.get_args(t)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin is typing.Literal:
        return " \\| ".join(f'`{a!r}`'.replace("'", '"') for a in args)
    if origin in (typing.Union, types.UnionType):
        parts = [a for a in args if a is not type(None)]
        names = [_type_name(a) for a in parts]
        return " \\| ".join(names) + (" (optional)" if len(parts) < len(args) else "")
    if origin in (list, tuple):
        inner = ", ".join(_type_name(a) for a in args if a is not Ellipsis)
        return f"[{inner}{', ...' if origin is list or Ellipsis in args else ''}]"
    if origin is dict:
        return "table"
    if isinstance(t, type) and issubclass(t, BaseModel):
        return f"table ({t.__name__})"
    return getattr(t, "__name__", str(t))


def _limits(field) -> str:
    """The field's limits, then those on its items (``items:``), as text."""
    marks = {at.Gt: (">", "gt"), at.Ge: (">=", "ge"), at.Lt: ("<", "lt"), at.Le: ("<=", "le")}

    def collect(meta) -> list[str]:
        found = []
        for m in meta:
            for cls, (sym, attr) in marks.items():
                if isinstance(m, cls):
                    found.append(f"{sym} {getattr(m, attr):g}")
            if isinstance(m, at.MinLen):
                found.append(f"length >= {m.min_length}")
            if isinstance(m, at.MaxLen):
                found.append(f"length <= {m.max_length}")
            if hasattr(m, "metadata"):
                found += collect(m.metadata)
        return found

    def unwrap(t):  # an optional's value, and the limits written on it
        meta = []
        while True:
            if typing.get_origin(t) is typing.Annotated:
                meta += list(typing.get_args(t)[1:])
                t = typing.get_args(t)[0]
            elif typing.get_origin(t) in (typing.Union, types.UnionType) and type(None) in typing.get_args(t):
                t = next(a for a in typing.get_args(t) if a is not type(None))
            else:
                return t, meta

    t, meta = unwrap(field.annotation)
    own = collect([*field.metadata, *meta])
    items = [x for a in typing.get_args(t) for x in collect(unwrap(a)[1])]
    text = ", ".join(dict.fromkeys(own))
    if items:
        text += ("; " if text else "") + "items: " + ", ".join(dict.fromkeys(items))
    return text


def _default(field) -> str:
    if field.default is PydanticUndefined and field.default_factory is None:
        return "*required*"
    value = field.default_factory() if field.default_factory is not None else field.default
    if isinstance(value, BaseModel):
        return "(its defaults)"
    if value is None:
        return "none"

    def toml(v):
        return [toml(x) for x in v] if isinstance(v, (list, tuple)) else v

    return f"`{toml(value)!r}`".replace("'", '"').replace("True", "true").replace("False", "false")


def _bases(model: type[BaseModel]) -> list[type[BaseModel]]:
    """The models ``model`` inherits fields from that describe them (a program's options: the options every program
    shares), nearest first."""
    return [c for c in model.__mro__[1:]
            if issubclass(c, BaseModel) and c is not BaseModel and c.__dict__.get("__doc__")]


def _described(model: type[BaseModel]) -> str:
    """The model's docstring, then those of the models it inherits fields from."""
    docs = [model.__doc__ or ""] + [c.__doc__ for c in _bases(model)]
    return "\n\n".join(inspect.cleandoc(d) for d in docs if d)


def _markdown(text: str) -> str:
    """reST literals and cross-references made code spans."""
    text = re.sub(r":\w+:`~?(?:virtual_vehicle\.)?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _doc(model: type[BaseModel], shown: dict | None = None) -> str:
    """The model's docstring and its bases' as Markdown; a base already described under another section (``shown``:
    base -> that section's path) is referred to there instead of repeated."""
    shown = {} if shown is None else shown
    parts = [inspect.cleandoc(model.__doc__ or "")]
    for base in _bases(model):
        if base in shown:
            fields = ", ".join(f"``{name}``" for name in base.model_fields if name not in ("kind", "program"))
            parts.append(textwrap.fill(f"Also the fields {fields}, described under ``{shown[base]}``.", 110))
        else:
            parts.append(inspect.cleandoc(base.__doc__))
    return _markdown("\n\n".join(p for p in parts if p))


def sections() -> Iterator[tuple[str, type[BaseModel]]]:
    """(TOML path, model) for every table of the format, the top level first."""
    seen: set[type[BaseModel]] = set()
    queue: list[tuple[str, type[BaseModel]]] = [("(top level)", S.Scenario)]
    while queue:
        path, model = queue.pop(0)
        if model in seen:
            continue
        seen.add(model)
        yield path, model
        for name, f in model.model_fields.items():
            inner = _models(f.annotation)
            base = name if path == "(top level)" else f"{path.split(' ')[0].strip('[]')}.{name}"  # tag dropped
            listed = typing.get_origin(f.annotation) is list or any(
                typing.get_origin(a) is list for a in typing.get_args(f.annotation))
            for m in inner:
                tag = next((t for t in ("kind", "program") if t in m.model_fields), None)  # what picks the table
                label = f"[[{base}]]" if listed else f"[{base}]"
                if tag is not None and len(inner) > 1:
                    label += f" {tag} = {typing.get_args(m.model_fields[tag].annotation)[0]!r}".replace("'", '"')
                queue.append((label, m))


def reference() -> str:
    """The whole reference page, Markdown."""
    out = [INTRO]
    shown: dict = {}
    for path, model in sections():
        out.append(f"## `{path}` ({model.__name__})\n")
        out.append(_doc(model, shown) + "\n")
        shown.update({base: path for base in _bases(model) if base not in shown})
        out.append("| field | type | default | limits |")
        out.append("|---|---|---|---|")
        for name, f in model.model_fields.items():
            out.append(f"| `{name}` | {_type_name(f.annotation)} | {_default(f)} | {_limits(f)} |")
        out.append("")
    return "\n".join(out)


def undocumented() -> list[str]:
    """Fields that their model's description does not name (``kind`` selectors excepted): should stay empty."""
    def named(name, doc):  # ``name``, ``name = ...``, ``name[k]`` or ``[table.name]``
        return re.search(r"``(\[[\w.]*\.)?" + re.escape(name) + r"(?!\w)", doc) is not None

    return [f"{model.__name__}.{name}" for _, model in sections() for name in model.model_fields
            if name != "kind" and not named(name, _described(model))]


if __name__ == "__main__":
    print(reference(), end="")
