"""Every bad input a new user tried (issue 30) ends the same way: exit code 2, exactly one message line that names
the field or the problem, no traceback, and nothing simulated or written first.

The cases run the real command (typer's CliRunner in this process; a few again as a subprocess, as the console
script runs them). A status line of a long phase ("building ... ...") may precede the message on a slow machine;
it is not a message and is left out of the count.
"""

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from virtual_vehicle.ui.cli import app

runner = CliRunner()

GOOD = """
name = "t"
duration = 0.5
[array]
kind = "grid"
nx = 5
ny = 4
pitch = 0.1
[field]
kind = "uniform"
velocity = [0.2, 0.0]
{extra}
[[parcels]]
name = "a"
length = 0.25
width = 0.2
mass = {mass}
mu = 1.0
x = {x}
y = 0.15
"""


def scenario(extra: str = "", mass: str = "1.0", x: str = "0.15", duration: str | None = None) -> str:
    text = GOOD.format(extra=extra, mass=mass, x=x)
    return text if duration is None else text.replace("duration = 0.5", duration)


# (case id, scenario text (None: a directory), the field or problem the one message must name)
SCENARIOS = [
    ("negative-mass", scenario(mass="-1.0"), "parcels[0].mass: must be positive (at least 1e-12), got -1.0"),
    ("tiny-mass", scenario(mass="1e-300"), "parcels[0].mass: must be at least 1e-12"),
    ("unknown-friction-law", scenario(extra='[friction]\nlaw = "rubber"'), "friction.law"),
    ("parcel-off-the-array", scenario(x="5.0"), "parcels[0].x"),
    ("malformed-toml", "duration = = 3\n[array\n", "not valid TOML"),
    ("directory-as-scenario", None, "is a directory"),
    ("huge-allocation", scenario(duration="duration = 1e6\noutput_dt = 1e-6"), "output_dt: this run would hold"),
    ("coarse-fixed-dt", scenario(extra='[integrator]\nmode = "fixed"\ndt = 0.5', duration="duration = 20.0"),
     "integrator.dt: 0.5 s cannot resolve the scene"),
    ("fixed-dt-10", scenario(extra='[integrator]\nmode = "fixed"\ndt = 10', duration="duration = 20.0"),
     "integrator.dt: 10 s cannot resolve the scene"),
]


def one_error(result, needle: str) -> None:
    """Exit 2, one message line naming ``needle``, no traceback, nothing on stdout."""
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip() and not ln.endswith(" ...")]
    assert len(lines) == 1, result.stderr
    assert needle in lines[0] and lines[0].startswith("error"), lines[0]
    assert result.stdout == ""


def write(tmp_path, text):
    path = tmp_path / "17_dir.toml"
    if text is None:
        path.mkdir()
    else:
        path.write_text(text)
    return path


@pytest.mark.parametrize("command", ["run", "check", "animate"])
@pytest.mark.parametrize("case,text,needle", SCENARIOS, ids=[c[0] for c in SCENARIOS])
def test_bad_scenarios(tmp_path, command, case, text, needle):
    path = write(tmp_path, text)
    out = tmp_path / ("o.gif" if command == "animate" else "o")
    args = [command, str(path)] + ([] if command == "check" else ["--out", str(out)])
    if command == "animate" and case == "huge-allocation":  # the video's own bound is met first: 2e7 frames
        needle = "--fps: 1e+06 s at speed 1 and 20 fps is 20000001 frames"
    one_error(runner.invoke(app, args), needle)
    assert not out.exists()


def test_out_naming_a_file(tmp_path):
    afile = tmp_path / "taken"
    afile.write_text("x")
    one_error(runner.invoke(app, ["run", str(write(tmp_path, scenario())), "--out", str(afile)]), "--out")
    assert afile.read_text() == "x"


def test_out_a_non_empty_foreign_folder(tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "thesis.tex").write_text("x")
    one_error(runner.invoke(app, ["run", str(write(tmp_path, scenario())), "--out", str(folder)]), "--out")
    assert [f.name for f in folder.iterdir()] == ["thesis.tex"]


def test_animate_into_a_folder(tmp_path):
    folder = tmp_path / "video.mp4"
    folder.mkdir()
    one_error(runner.invoke(app, ["animate", str(write(tmp_path, scenario())), "--out", str(folder)]),
              "is a folder")


def test_checkpoint_that_is_not_one(tmp_path):
    fake = tmp_path / "fake.ckpt"
    fake.write_bytes(b"PK\x03\x04 not a checkpoint")
    one_error(runner.invoke(app, ["resume", str(fake), "--out", str(tmp_path / "o")]), "fake.ckpt")


def test_resume_into_a_file(tmp_path):
    fake = tmp_path / "fake.ckpt"
    fake.write_bytes(b"whatever")
    afile = tmp_path / "taken"
    afile.write_text("x")
    one_error(runner.invoke(app, ["resume", str(fake), "--out", str(afile)]), "--out")


def test_compare_over_an_earlier_comparison(tmp_path):
    out = tmp_path / "cmp"
    out.mkdir()
    (out / "compare.json").write_text("{}")
    one_error(runner.invoke(app, ["compare", "sorting_junction", "--out", str(out)]), "--force")


@pytest.mark.parametrize("case", ["negative-mass", "tiny-mass", "directory-as-scenario", "huge-allocation",
                                  "coarse-fixed-dt"])
def test_the_console_script_says_it_once(tmp_path, case):
    _, text, needle = next(c for c in SCENARIOS if c[0] == case)
    path = write(tmp_path, text)
    proc = subprocess.run([sys.executable, "-m", "virtual_vehicle.ui.cli", "run", str(path), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and proc.stdout == ""
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and not ln.endswith(" ...")]
    assert len(lines) == 1 and needle in lines[0], proc.stderr


@pytest.mark.parametrize("fps", ["100000", "0.01"])
def test_animate_frames_per_second_out_of_range(tmp_path, fps):
    out = tmp_path / "o.gif"
    one_error(runner.invoke(app, ["animate", str(write(tmp_path, scenario())), "--out", str(out), "--fps", fps]),
              "--fps")
    assert not out.exists()


def sweep_file(tmp_path, vary: str) -> str:
    (tmp_path / "base.toml").write_text(scenario())
    path = tmp_path / "study.toml"
    path.write_text(f'base = "base.toml"\n[vary]\n{vary}\n')
    return str(path)


def test_sweep_with_a_misspelt_vary_path(tmp_path):
    out = tmp_path / "study"
    one_error(runner.invoke(app, ["sweep", sweep_file(tmp_path, '"frictio.law" = ["coulomb", "viscous"]'),
                                  "--out", str(out)]), "vary.frictio.law")
    assert not out.exists()


def test_sweep_against_an_unreachable_scheduler(tmp_path):
    import socket

    with socket.socket() as s:  # a port that nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "study"
    one_error(runner.invoke(app, ["sweep", sweep_file(tmp_path, '"parcels.0.mass" = [1.0, 2.0]'), "--out", str(out),
                                  "--scheduler", f"tcp://127.0.0.1:{port}"]), "--scheduler")


def test_checkpoint_into_a_folder_or_under_a_file_before_anything_runs(tmp_path):
    path = write(tmp_path, scenario())
    afile = tmp_path / "taken"
    afile.write_text("x")
    for target, needle in ((tmp_path, "is a folder"), (afile / "c.ckpt", "is a file, not a folder")):
        one_error(runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "o"), "--checkpoint", str(target)]),
                  "--checkpoint: ")
        assert needle in runner.invoke(app, ["run", str(path), "--out", str(tmp_path / "o"), "--checkpoint",
                                             str(target)]).stderr
    assert not (tmp_path / "o").exists()


def test_sweep_fault_study_and_layout_out_under_a_file(tmp_path):
    afile = tmp_path / "taken"
    afile.write_text("x")
    sweep = sweep_file(tmp_path, '"parcels.0.mass" = [1.0, 2.0]')
    one_error(runner.invoke(app, ["sweep", sweep, "--out", str(afile)]), "--out")
    one_error(runner.invoke(app, ["fault-study", "sorting_junction", "--out", str(afile / "s")]), "--out")
    one_error(runner.invoke(app, ["layout", "prototype_18", "--out", str(afile / "l.png")]), "--out")
    assert afile.read_text() == "x"


def test_fault_study_with_a_rate_twice(tmp_path):
    one_error(runner.invoke(app, ["fault-study", "sorting_junction", "--rates", "0.1,0.1", "--out",
                                  str(tmp_path / "s")]), "rates")
