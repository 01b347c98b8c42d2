"""Issue 44, hole 8: every number `omnigen render` and `omnigen convert kitti|dair` take is checked
when it is parsed, the range in the message, before anything is written.

Before: `--width 0` rendered at the rig's 640 without a word, `--seed 10**24` failed at the first
record after that frame's image, depth and instance files were written, `--precipitation 5` was
clamped to 1 without a word, `--workers 0` ran one process. Parsing only: no frame is rendered.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from omnigen.cli import build_parser, main
from omnigen.options import SEED_MAX

# Cheap to render should a check ever be missed: the failing test then writes a tiny raster frame.
RENDER = ["render", "--rig", "pole", "--frames", "1", "--scene", "tiny", "--backend", "raster",
          "--width", "32", "--height", "24"]


def _refused(argv: list[str], capsys) -> str:
    """argparse's usage error (exit 2) for `argv`; its stderr."""
    with pytest.raises(SystemExit) as refused:
        main(argv)
    assert refused.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("option, value, message", [
    ("--width", "0", "argument --width: 0 is outside [8, 8192]"),
    ("--height", "9000", "argument --height: 9000 is outside [8, 8192]"),
    ("--frames", "0", "argument --frames: 0 is outside [1, 10000000]"),
    ("--start", "-1", "argument --start: -1 is outside [0, "),
    ("--seed", "-1", "argument --seed: -1 is outside [0, "),
    ("--precipitation", "5", "argument --precipitation: 5 is outside [0, 1]"),
    ("--precipitation", "-0.5", "argument --precipitation: -0.5 is outside [0, 1]"),
    ("--fog-density", "-1", "argument --fog-density: -1 is outside [0, 1]"),
    ("--fog-density", "nan", "argument --fog-density: nan is not a finite number; expected one in [0, 1]"),
    ("--ray-workers", "0", "argument --ray-workers: 0 is outside [1, 10000]"),
    ("--cpus-per-worker", "0", "argument --cpus-per-worker: 0 is outside [0.0001, 1024]"),
    ("--frames-per-worker", "0", "argument --frames-per-worker: 0 is outside [1, 10000000]"),
    ("--retries", "-1", "argument --retries: -1 is outside [0, 100]"),
    ("--shard", "4/3", "argument --shard: need 1 <= K <= N"),
])
def test_render_numbers_are_refused_when_parsed_with_the_range(tmp_path, capsys, option, value, message):
    out = tmp_path / "ds"
    assert message in _refused([*RENDER, option, value, "--out", str(out)], capsys)
    assert not out.exists()


def test_a_seed_past_int64_is_refused_before_anything_is_written(tmp_path, capsys):
    """It failed at the first record, after that frame's image, depth and instance files."""
    out = tmp_path / "ds"
    err = _refused([*RENDER, "--seed", str(10**24), "--out", str(out)], capsys)
    assert f"argument --seed: {10**24} is outside [0, " in err
    assert not out.exists()
    assert _refused([*RENDER, "--seed", str(SEED_MAX + 1), "--out", str(out)], capsys)
    assert build_parser().parse_args([*RENDER, "--seed", str(SEED_MAX), "--out", str(out)]).seed == SEED_MAX


def test_frame_indices_past_int64_are_refused_before_anything_is_written(tmp_path, capsys):
    """--start and --frames each in range, but the run's last index past int64: refused as the
    job is made, before the folder is claimed."""
    out = tmp_path / "ds"
    assert main([*RENDER, "--frames", "2", "--start", str(SEED_MAX), "--out", str(out)]) == 1  # the later --frames counts
    assert "the last frame index, start + frames - 1 = 9223372036854775808, is past" in capsys.readouterr().err
    assert not out.exists()


def test_the_render_job_refuses_what_the_command_line_does(tmp_path):
    """API callers (benchmarks, Ray actors) get the same checks: a width of 0 no longer means the rig's."""
    from omnigen.rigs.render import RenderJob

    for bad, match in (({"width": 0}, "--width 0 is outside"), ({"seed": 10**24}, "--seed"),
                       ({"start": -1}, "--start -1"), ({"height": 2.5}, "--height 2.5")):
        with pytest.raises(ValueError, match=match):
            RenderJob(rig="pole", frames=1, out=tmp_path, **bad)
    assert RenderJob(rig="pole", frames=1, out=tmp_path, seed=np.int64(3), width=np.int64(64)).seed == 3


def test_fixed_weather_outside_its_range_is_refused_not_clamped():
    """draw_weather clamped a precipitation of 5 to 1: the frame showed other weather than asked."""
    from omnigen.scenes.weather import draw_weather

    rng = np.random.default_rng(0)
    for kw in ({"precipitation": 5.0}, {"precipitation": -0.1}, {"fog_density": float("nan")}, {"fog_density": 2.0}):
        with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
            draw_weather(rng, {"rain": 1.0}, **kw)
    assert draw_weather(rng, {"rain": 1.0}, precipitation=1.0, fog_density=0.0).precipitation == 1.0


@pytest.mark.parametrize("argv, message", [
    (["kitti", "--limit", "0"], "argument --limit: 0 is outside [1, inf)"),
    (["kitti", "--workers", "0"], "argument --workers: 0 is outside [1, 256]"),
    (["dair", "--workers", "-2"], "argument --workers: -2 is outside [1, 256]"),
    (["dair", "--group-gap", "-1"], "argument --group-gap: -1 is outside [0, 86400]"),
    (["dair", "--group-gap", "inf"], "argument --group-gap: inf is not a finite number; expected one in [0, 86400]"),
])
def test_convert_numbers_are_refused_when_parsed_with_the_range(tmp_path, capsys, argv, message):
    out = tmp_path / "ds"
    dataset, *options = argv
    assert message in _refused(["convert", dataset, str(tmp_path / "src"), "--out", str(out), *options], capsys)
    assert not out.exists()


def _parsers() -> dict[str, argparse.ArgumentParser]:
    def sub(p: argparse.ArgumentParser, dest: str) -> dict[str, argparse.ArgumentParser]:
        return next(a for a in p._actions if a.dest == dest).choices

    verbs = sub(build_parser(), "command")
    converters = sub(verbs["convert"], "converter")
    return {"render": verbs["render"], "convert kitti": converters["kitti"], "convert dair": converters["dair"]}


NUMERIC = {
    "render": {"--frames", "--seed", "--width", "--height", "--start", "--fog-density", "--precipitation", "--shard",
               "--sequence-length", "--fps", "--ray-workers", "--cpus-per-worker", "--frames-per-worker", "--retries"},
    "convert kitti": {"--limit", "--workers"},
    "convert dair": {"--limit", "--workers", "--group-gap"},
}


def test_every_numeric_option_has_a_checked_type_and_its_default_in_the_help():
    """No bare int or float is left: each number goes through omnigen.options (or --shard's K/N
    check), and its help says what it is when not given."""
    for name, parser in _parsers().items():
        checked = set()
        for action in parser._actions:
            assert action.type not in (int, float), f"{name} {action.option_strings}: unchecked {action.type.__name__}"
            if getattr(action.type, "__name__", "") in ("integer", "number", "_shard"):
                checked.add(action.option_strings[0])
                assert action.required or "default" in action.help, f"{name} {action.option_strings}: no default"
        assert checked == NUMERIC[name]


def test_a_rig_name_no_frame_id_can_hold_is_refused_before_anything_is_written(tmp_path, capsys):
    """The rig's name is part of every frame id: `name = "my pole"` failed at the first record,
    after that frame's image, depth and instance files were written."""
    from omnigen.rigs.rig import load_rig

    pole = Path(__file__).parents[2] / "rigs" / "presets" / "pole.toml"
    rig = tmp_path / "mine.toml"
    rig.write_text('name = "my pole"\n' + pole.read_text())
    with pytest.raises(ValueError, match=r"mine\.toml: field 'name': 'my pole' must be at most 64 letters"):
        load_rig(rig)
    spaced = tmp_path / "my pole.toml"  # no name in the file: the file's name, and the message says so
    spaced.write_text(pole.read_text())
    with pytest.raises(ValueError, match=r"'my pole' \(the file's name: set name = \"...\" in it\)"):
        load_rig(spaced)
    out = tmp_path / "ds"
    assert main([*RENDER, "--rig", str(rig), "--out", str(out)]) == 1  # the later --rig counts
    assert "field 'name'" in capsys.readouterr().err and not out.exists()


def test_a_fifo_as_the_render_arguments_file_is_refused_not_waited_on(tmp_path, capsys):
    """A FIFO put where a render folder keeps its arguments would block the resumed render for
    ever on the read: it is refused as not a regular file, at once."""
    import os
    import signal

    from omnigen.cli import main

    out = tmp_path / "render"
    out.mkdir()
    os.mkfifo(out / ".render-args.json")
    signal.signal(signal.SIGALRM, lambda *_: (_ for _ in ()).throw(TimeoutError("the render waited on the FIFO")))
    signal.alarm(20)
    try:
        code = main(["render", "--rig", "ego", "--frames", "1", "--width", "32", "--height", "24",
                     "--backend", "raster", "--out", str(out)])
    finally:
        signal.alarm(0)
    assert code == 1
    err = capsys.readouterr().err
    assert ".render-args.json" in err and "not a regular file" in err
