"""A cell program is one module (its options, builder, report, pictures' markers) registered by name: every
registered one keeps the cell-program contract, the scenario format is their union, a program registered in a copy
of the registry runs without touching any other file, and no code outside the modules dispatches on a program's
name."""

import re
import sys
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from typer.testing import CliRunner

from virtual_vehicle.cells.network.messages import Mailbox, Schema
from virtual_vehicle.cells.network.programs import check_program
from virtual_vehicle.cells.programs import PROGRAMS, owners, program_of
from virtual_vehicle.cells.programs.base import BuildContext, ControlSetup, ProgramOptions, no_markers, setup_for
from virtual_vehicle.config.scenario import (Scenario, bundled_scenarios, control_spec, dump_toml, load_scenario,
                                             parse_scenario, parse_text)
from virtual_vehicle.errors import ScenarioError
from virtual_vehicle.run.sim import run_network
from virtual_vehicle.ui.cli import app

SRC = Path(__file__).resolve().parents[1] / "src" / "virtual_vehicle"

ROW = {"kind": "row", "n": 8, "pitch": 0.1}
BOX = {"name": "box", "length": 0.25, "width": 0.1, "mass": 1.0, "mu": 0.5, "x": 0.25, "y": 0.0}


def example(name: str) -> Scenario:
    """A scenario running program ``name``, distributed: a bundled one where there is one, else a row of cells."""
    for bundled in bundled_scenarios():
        sc = load_scenario(bundled)[0]
        if sc.control is not None and sc.control.program == name and not getattr(sc.control, "central", False):
            return sc
    if name == "reserve":  # the junction's stream under the central reservation router
        sc = load_scenario("sorting_junction")[0]
        return sc.model_copy(update={"control": PROGRAMS[name].Options(**(sc.control.model_dump()
                                                                          | {"program": name}))})
    if name == "diffusion":
        return parse_scenario({"duration": 0.2, "array": ROW, "friction": {"law": "viscous"}, "parcels": [BOX],
                               "control": {"program": "diffusion", "sources": [[0, 0.1, 0.0]]}})
    raise AssertionError(f"no example scenario for program {name!r}: add one here")


@pytest.mark.parametrize("name", list(PROGRAMS))
def test_every_registered_program_keeps_the_cell_program_contract(name):
    setup = example(name).build()
    ctl = setup.control
    assert program_of(setup.scenario.control) is PROGRAMS[name]
    seen = setup.sensors.read(setup.specs, setup.states, np.random.default_rng(0))
    assert seen.any()  # the parcels are in sight: the program has something to act on
    check_program(ctl.program, ctl.topology, ctl.config, ticks=6, sensors=seen)


@pytest.mark.parametrize("name", list(PROGRAMS))
def test_every_program_module_has_the_whole_module_contract(name):
    module = PROGRAMS[name]
    assert issubclass(module.Options, ProgramOptions)
    assert module.Options.model_fields["program"].annotation == Literal[name]
    assert callable(module.build) and callable(module.markers)
    assert (module.report is None) == (module.SUMMARY is None) == (not module.COMPARED)
    assert isinstance(module.CENTRAL, bool) and isinstance(module.LABELS, bool)
    assert module.Options(program=name, **({"targets": [[0, 0, 0]]} if name == "pose" else {})).top_speed() >= 0


@pytest.mark.parametrize("name", sorted(bundled_scenarios()))
def test_every_bundled_scenario_parses_and_round_trips(name):
    sc, text = load_scenario(name)
    assert parse_text(dump_toml(sc)) == sc
    if sc.control is not None:
        assert type(sc.control) is PROGRAMS[sc.control.program].Options


def test_the_pictures_mark_what_the_program_module_says():
    setup = load_scenario("sorting_junction")[0].build()
    marks = program_of(setup.scenario.control).markers(setup)
    assert [k for _, k, _ in marks.lanes] == [-1, 0, 1, 2]  # the entry, then exits 0..2
    assert marks.destinations == [p.destination for p in setup.scenario.parcels]
    pose = example("pose").build()
    assert program_of(pose.scenario.control).markers(pose).targets == list(pose.scenario.control.targets)
    assert program_of(example("shuttle").control).markers(None).lanes == []


@pytest.mark.parametrize("control, words", [
    ({"program": "conveyor"}, r'control.program: unknown program "conveyor"; the programs are "shuttle", '),
    ({"speed": 0.2}, r'control.program: missing: name the program every cell runs, one of "shuttle"'),
    ({"program": "shuttle", "gap": 3}, r'control.gap: is a field of program "sort" or "reserve", not of program "shuttle"'),
    ({"program": "diffusion", "speed": 0.3}, r'control.speed: is a field of program "shuttle", "pose", "sort" or "reserve", '
                                             r'not of program "diffusion"'),
    ({"program": "sort", "gapp": 3}, r"control.gapp: unknown field"),
    ({"program": "pose"}, r"control.targets: Field required"),
])
def test_a_wrong_control_table_is_named_in_one_line(control, words, tmp_path):
    data = {"duration": 1.0, "array": ROW, "parcels": [BOX], "control": control}
    with pytest.raises(ScenarioError, match=words) as exc:
        parse_scenario(data)
    assert "\n" not in str(exc.value)
    path = tmp_path / "bad.toml"
    path.write_text(dump_toml_dict(data))
    r = CliRunner().invoke(app, ["check", str(path)])
    assert r.exit_code == 2
    assert re.search(words, " ".join(r.output.split()))


def dump_toml_dict(data: dict) -> str:
    import tomli_w

    return tomli_w.dumps(data)


def test_stray_fields_are_told_by_their_owners():
    assert owners("gap") == ["sort", "reserve"] and owners("targets") == ["pose"] and owners("period") == list(PROGRAMS)
    assert owners("nonsense") == []


# --------------------------------------------------------------------------- a program added in this file only

class PushSeen:
    """A trivial cell program: a cell that sees a parcel drives wheel 0 at ``speed`` (m/s); no sentences."""

    schema = Schema(())
    stationary = True

    def __init__(self, speed: float):
        self.speed = float(speed)

    def init(self, n, ports, config):
        return {"seen": np.zeros(n, dtype=bool)}

    def step(self, state, inputs):
        n, ports = inputs.connected.shape
        seen = np.asarray(inputs.sensors, bool).any(axis=1)
        wheels = np.zeros((n, 2))
        wheels[:, 0] = np.where(seen, self.speed, 0.0)
        return {"seen": seen}, Mailbox.empty(self.schema, n, ports), wheels


class ToyOptions(ProgramOptions):
    """``program = "toy"``: cells that see a parcel push it along wheel 0 at ``speed`` (m/s)."""

    program: Literal["toy"]
    speed: float = 0.1

    def top_speed(self) -> float:
        return self.speed


Options = ToyOptions


def build(options: ToyOptions, ctx: BuildContext) -> ControlSetup:
    return setup_for(options, ctx, PushSeen(options.speed))


report = None
SUMMARY = None
COMPARED = ()
CENTRAL = False
LABELS = False
markers = no_markers

REGISTRY = {**PROGRAMS, "toy": sys.modules[__name__]}
ToyControl = control_spec(REGISTRY)


class ToyScenario(Scenario):
    control: ToyControl | None = None


def test_a_program_registered_in_a_copy_of_the_registry_builds_and_runs():
    data = {"duration": 1.0, "array": ROW, "friction": {"law": "viscous"}, "parcels": [BOX],
            "control": {"program": "toy", "speed": 0.1, "period": 0.02}}
    with pytest.raises(ScenarioError, match='unknown program "toy"'):
        parse_scenario(data)  # the package's own registry does not know it
    setup = ToyScenario.model_validate(data).build()
    assert isinstance(setup.control.program, PushSeen) and setup.control.period == 0.02
    check_program(setup.control.program, setup.control.topology, setup.control.config,
                  sensors=setup.sensors.read(setup.specs, setup.states, np.random.default_rng(0)))
    result = run_network(setup)
    x = result.parcels[0].trajectory.states[:, 0]
    assert x[-1] > x[0] + 0.05  # pushed along +x by the cells under it
    assert "toy" not in result.summary() and "sorting" not in result.summary()
    assert "toy" not in PROGRAMS


# --------------------------------------------------------------------------- dispatch stays in the modules

DISPATCH = re.compile(r"\bprogram\s*(==|!=)|\.program\s+(not\s+)?in\b|\[[\w.]*\.program\]")


def test_no_code_outside_the_program_modules_dispatches_on_a_program_name():
    found = [f"{path.relative_to(SRC)}:{k}: {line.strip()}"
             for path in sorted(SRC.rglob("*.py")) if "programs" not in path.relative_to(SRC).parts[:2]
             for k, line in enumerate(path.read_text().splitlines(), 1) if DISPATCH.search(line)]
    assert found == []
    assert DISPATCH.search('if sc.control.program == "sort":') and DISPATCH.search("TABLE[sc.control.program]")
