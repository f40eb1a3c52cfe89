"""Issue 17: never destroy a file, never hang past Ctrl-C, never return a silently wrong
number. One test (or group) per numbered reproduction of the issue; each failed before
the fix. Hangs run in a child process under a timeout, interrupts are a real SIGINT to a
child process. (Reproduction 6, hot cells and refinement, is in test_refinement.py.)"""
from __future__ import annotations

import json
import os
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import SCENES, camera, grid, media_scene, render, start_cli
from mitsuba_plugins import output
from mitsuba_plugins.grids import gridio
from mitsuba_plugins.tools import cli, compare as cmp

ROOT = Path(__file__).resolve().parents[2]
CORNELL = str(SCENES / "cornell_box.xml")


def run_cli(*args, timeout=300, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mitsuba_plugins.tools.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT, **kw)


def render_args(out, *extra):
    return ["render", CORNELL, "--res", "16", "--spp", "1", "-o", str(out), *extra]


# -- 1. an output path with the wrong extension is refused before it is touched ----------
@pytest.mark.parametrize("name", ["my_scene.xml", "notes.txt", "noext", "out.png"])
def test_render_refuses_extension_without_touching_the_file(tmp_path, capsys, name):
    target = tmp_path / name
    target.write_text("precious")
    assert cli.main(render_args(target)) == 2
    err = capsys.readouterr().err
    assert f"-o/--output '{target}'" in err and "allowed: .exr" in err, err
    assert target.read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


# -- 2. a write that fails part-way leaves the old file whole -------------------------------
def _limit_file_size():
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))


def test_failed_write_keeps_the_old_file(tmp_path):
    """Under ``ulimit -f`` (20 kB) a 128x128 EXR (one channel in mono: 64 kB) cannot be written: the render fails, and the
    good ``keep.exr`` and its ``keep.png`` are left byte for byte, with no temporary file.
    In a CUDA variant OptiX's on-disk kernel cache is turned off (``OPTIX_CACHE_MAXSIZE=0``):
    under the same limit its database cannot be written and Dr.Jit aborts before rendering."""
    keep = tmp_path / "keep.exr"
    old = {keep: b"good exr", keep.with_suffix(".png"): b"good png"}
    for path, data in old.items():
        path.write_bytes(data)
    proc = run_cli("render", CORNELL, "--res", "128", "--spp", "1", "-o", keep,
                   preexec_fn=_limit_file_size,
                   env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "OPTIX_CACHE_MAXSIZE": "0"})
    assert proc.returncode == 2, proc.stderr
    assert f"mitsuba-plugins: error: output '{keep}': could not be written (" in proc.stderr
    assert "File too large); the file that was there is unchanged" in proc.stderr
    for path, data in old.items():
        assert path.read_bytes() == data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr", "keep.png"]


def test_atomic_path_failure_leaves_target_and_no_temporary(tmp_path):
    target = tmp_path / "table.md"
    target.write_text("old")
    with pytest.raises(output.OutputError,
                       match="output '.*table.md': could not be written \\(disk full\\); the file "
                             "that was there is unchanged"):
        with output.atomic_path(target) as tmp:
            Path(tmp).write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["table.md"]
    output.write_text(target, "new")
    assert target.read_text() == "new" and len(list(tmp_path.iterdir())) == 1


def test_json_outputs_are_strict():
    text = output.dumps_json({"a": float("inf"), "b": [float("nan"), 1.5], "c": np.float32(2)})
    assert json.loads(text, parse_constant=lambda c: pytest.fail(c)) == \
        {"a": None, "b": [None, 1.5], "c": 2.0}


# -- 3. every target is checked first; nothing is written when one is blocked -----------------
def test_render_with_a_folder_in_the_way_of_the_preview(tmp_path, capsys):
    (tmp_path / "x.png").mkdir()
    assert cli.main(render_args(tmp_path / "x.exr")) == 2
    err = capsys.readouterr().err
    assert f"'{tmp_path / 'x.png'}': a folder of that name is in the way" in err, err
    assert not (tmp_path / "x.exr").exists()


def test_compare_with_a_folder_in_the_way_writes_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    (out / "panel.png").mkdir(parents=True)
    rc = cli.main(["compare", CORNELL, "-i", "path_rr:max_depth=2", "--res", "8", "--spp", "4",
                   "--passes", "2", "--ref-spp", "16", "--cache", str(tmp_path / "c"),
                   "-o", str(out), "-q"])
    assert rc == 2
    assert "panel.png': a folder of that name is in the way" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["panel.png"]
    assert not (tmp_path / "c").exists()   # refused before the reference was rendered


# -- 4. a file where a folder should be --------------------------------------------------------
def test_output_below_a_regular_file(tmp_path, capsys):
    blocker = tmp_path / "some_regular_file"
    blocker.write_text("x")
    assert cli.main(render_args(blocker / "x.exr")) == 2
    err = capsys.readouterr().err
    assert f"'{blocker}' is a file, not a folder" in err, err
    assert blocker.read_text() == "x"


# -- 5. float32 overflow of the extinction is refused -------------------------------------------
def _grid_scene(path, **kw):
    return {"type": "scene", "m": {"type": "grid_medium", "filename": str(path), **kw}}


def test_scale_beyond_float32_is_refused(tmp_path):
    path = tmp_path / "g.npy"
    np.save(path, np.ones((4, 4, 4), np.float32))
    with pytest.raises(Exception, match="parameter 'scale' = 1e\\+39 is invalid"):
        mi.load_dict(_grid_scene(path, scale=1e39))
    with pytest.raises(Exception, match="extinction too large: parameter 'scale' = 1e\\+32"):
        mi.load_dict(_grid_scene(path, scale=1e32))


def test_float_max_vol_is_refused(tmp_path):
    path = tmp_path / "max.vol"
    gridio.write_vol(path, np.full((4, 4, 4), np.finfo(np.float32).max, np.float32))
    with pytest.raises(Exception, match="extinction too large.*max.vol"):
        mi.load_dict(_grid_scene(path))


def test_voxel_optical_depth_is_bounded(tmp_path):
    path = tmp_path / "v.npy"
    data = np.zeros((8, 8, 8), np.float32)
    data[4, 3, 5] = 1e20
    np.save(path, data)
    with pytest.raises(Exception, match="optical depth 1.25e\\+19.*allowed: at most 1e\\+08"):
        mi.load_dict(_grid_scene(path))


# -- 7. a runaway march step is refused --------------------------------------------------------
def test_tiny_step_size_is_refused_at_render_time():
    scene = media_scene(grid(), sensor=camera(res=8))
    with pytest.raises(Exception) as error:   # raised while the kernel is traced
        render(scene, {"type": "volpath_raymarch", "mode": "single", "step_size": 1e-9}, spp=1)
    assert re.search("'step_size' = 1e-09 would cut a march.*allowed: >= 3.46e-05 here",
                     cli.user_message(error.value)), cli.user_message(error.value)


@pytest.mark.parametrize("mode", ["single", "multi"])
def test_tiny_step_optical_depth_is_refused_at_render_time(mode):
    """Issue 46.6: ``step_mode = majorant`` with ``step_optical_depth = 1e-9`` rendered
    16x16 at 1 spp in 94 s instead of refusing; the densest majorant cell bounds the
    steps of a march as the step size does."""
    scene = media_scene(grid(), sensor=camera(res=8))
    with pytest.raises(Exception) as error:
        render(scene, {"type": "volpath_raymarch", "mode": mode, "step_mode": "majorant",
                       "step_optical_depth": 1e-9}, spp=1)
    assert re.search(r"'step_optical_depth' = 1e-09 would cut a march .*majorant optical "
                     r"depth up to about [0-9.]+\).*allowed: >= [0-9.e-]+ here \(at most "
                     r"100000 steps",
                     cli.user_message(error.value)), cli.user_message(error.value)
    # the default renders
    assert render(scene, {"type": "volpath_raymarch", "mode": mode, "step_mode": "majorant"},
                  spp=1).mean() > 0


# -- 8. Ctrl-C stops any command within a second or two, the same way everywhere ----------------
def _interrupt(args, wait_for: str | None, delay: float):
    """Start the CLI, SIGINT it ``delay`` seconds after ``wait_for`` appears on its stderr
    (or after its start): ``(exit status, seconds from the signal to the exit, stderr)``."""
    with start_cli(*args, cwd=ROOT) as proc:
        try:
            if wait_for:
                for line in proc.stderr:
                    if wait_for in line:
                        break
            time.sleep(delay)
            assert proc.poll() is None, "the command ended before it was interrupted"
            sent = time.perf_counter()
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=10)
            return proc.returncode, time.perf_counter() - sent, proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()


@pytest.mark.parametrize("integrator", ["path_rr", "path"])
def test_ctrl_c_stops_a_long_render(tmp_path, integrator):
    """SIGINT 1.5 s into a render kernel of ~1e9 samples (minutes): exit status 130 and
    'mitsuba-plugins: interrupted' within 2 s, for our integrator and a built-in alike,
    and no output or temporary file left."""
    rc, seconds, err = _interrupt(
        ["render", CORNELL, "--res", "128", "--spp", "65536", "-i", integrator,
         "-o", tmp_path / "long.exr"], wait_for="rendering", delay=1.5)
    assert rc == cli.EXIT_INTERRUPTED, err
    assert "mitsuba-plugins: interrupted" in err
    assert seconds < 2.0, f"took {seconds:.2f} s to stop"
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_stops_compare_while_it_renders_a_reference(tmp_path):
    rc, seconds, err = _interrupt(
        ["compare", CORNELL, "-i", "path_rr", "--res", "128", "--ref-spp", "1048576",
         "--cache", tmp_path / "c", "-o", tmp_path / "o", "-q"], wait_for=None, delay=4.0)
    assert rc == cli.EXIT_INTERRUPTED and "mitsuba-plugins: interrupted" in err, err
    assert seconds < 2.0, f"took {seconds:.2f} s to stop"
    assert not any(p.is_file() for p in tmp_path.rglob("*"))


# -- 10. reference-cache entries are verified on every read, and rebuilt when damaged ------------
def _damage(path: Path, how: str):
    raw = path.read_bytes()
    if how == "truncated":
        path.write_bytes(raw[: len(raw) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(os.urandom(len(raw)))
    elif how == "bit_flip":
        flipped = bytearray(raw)
        flipped[len(raw) // 2] ^= 0x10
        path.write_bytes(bytes(flipped))
    else:
        with np.load(path) as data:
            fields = {k: data[k] for k in data.files}
        if how == "missing_key":
            del fields["se"]
        elif how == "nan_mean":
            fields["mean"] = np.full_like(fields["mean"], np.nan)
        elif how == "zeros":
            fields["mean"] = np.zeros_like(fields["mean"])
        elif how == "scaled":
            fields["mean"] = fields["mean"] * 0.5
        elif how == "wrong_shape":   # consistent checksum: only the shape check can tell
            fields["mean"] = fields["se"] = np.zeros((4, 4, 3))
            fields["checksum"] = np.str_(cmp._cache_checksum(fields))
        with open(path, "wb") as f:
            np.savez(f, **fields)


@pytest.mark.parametrize("how", ["truncated", "empty", "garbage", "bit_flip", "missing_key",
                                 "nan_mean", "zeros", "scaled", "wrong_shape"])
def test_damaged_cache_entry_is_rebuilt(tmp_path, capsys, how):
    def reference():
        result = cmp.compare(CORNELL, [{"type": "path_rr", "max_depth": 2}], spp=4, passes=2,
                             ref_spp=32, res=8, cache_dir=tmp_path, progress=False)
        return next(iter(result.references.values()))

    fresh = reference()
    (entry,) = tmp_path.glob("*.npz")
    capsys.readouterr()
    _damage(entry, how)
    rebuilt = reference()
    err = capsys.readouterr().err
    assert f"reference cache entry '{entry}' is damaged (" in err and "rebuilding it" in err, err
    np.testing.assert_allclose(rebuilt.mean, fresh.mean, rtol=1e-5, atol=1e-7)
    again = reference()   # the rebuilt entry is good again: read without a word
    assert capsys.readouterr().err == ""
    np.testing.assert_array_equal(again.mean, rebuilt.mean)


# -- 11. a singular to_world is refused ----------------------------------------------------
@pytest.mark.parametrize("scale", [[2.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
def test_singular_to_world_is_refused(tmp_path, scale):
    path = tmp_path / "g.npy"
    np.save(path, np.ones((4, 4, 4), np.float32))
    with pytest.raises(Exception, match="parameter 'to_world' is singular"):
        mi.load_dict(_grid_scene(path, to_world=mi.ScalarTransform4f().scale(scale)))


# -- 12. one correct line and the right exit status for each bad input ----------------------------
@pytest.mark.parametrize("res", ["0", "-3"])
def test_render_res_must_be_positive(capsys, tmp_path, res):
    assert cli.main(["render", CORNELL, "--res", res, "-o", str(tmp_path / "a.exr")]) == 2
    assert f"--res = {res} is invalid; allowed: an integer in [1, 16384]" in capsys.readouterr().err


def test_render_seed_range(capsys, tmp_path):
    assert cli.main(render_args(tmp_path / "a.exr", "--seed", "-1")) == 2
    assert "--seed = -1 is invalid; allowed: an integer in [0, 4294967295]" in \
        capsys.readouterr().err
    assert cli.main(render_args(tmp_path / "a.exr", "--seed", str(2 ** 32 - 1))) == 0


def test_grid_info_exit_status_and_options(tmp_path, capsys):
    bad = tmp_path / "bad.npy"
    np.save(bad, np.array([[[np.nan, 1.0], [1.0, 1.0]]] * 2, np.float32))
    assert cli.main(["grid", "info", str(bad)]) == 1
    captured = capsys.readouterr()
    assert "INVALID" in captured.out and "1 of 1 grid file(s) invalid" in captured.err
    for value in ("0", "-3", "2000"):
        assert cli.main(["grid", "info", str(bad), "--majorant-resolution", value]) == 2
        assert f"--majorant-resolution = {value} is invalid; allowed: an integer in [1, 1024]" \
            in capsys.readouterr().err


def test_grid_info_json_has_no_infinity(tmp_path, capsys):
    empty = tmp_path / "empty.npy"
    np.save(empty, np.zeros((4, 4, 4), np.float32))
    assert cli.main(["grid", "info", str(empty), "--json"]) == 0
    info = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(c))
    assert info["max_over_mean"] is None and "null" in info["null_means"]


def _fifo(path):
    os.mkfifo(path)


def _loop(path):
    os.symlink(path.with_name("loop_b.vol"), path)
    os.symlink(path, path.with_name("loop_b.vol"))


@pytest.mark.parametrize("make, message", [
    (lambda p: p.mkdir(), "is a folder, not a grid file"),
    (_fifo, "is a FIFO (named pipe), not a regular file"),
    (_loop, "a symbolic link loop"),
    (lambda p: os.symlink(p.with_name("gone.vol"), p), "which does not exist"),
    (lambda p: None, "file does not exist"),
])
@pytest.mark.parametrize("suffix", [".vol", ".npy", ".vdb"])
def test_grid_file_kinds_are_named(tmp_path, make, message, suffix):
    path = tmp_path / f"g{suffix}"
    make(path)
    with pytest.raises(gridio.GridFileError,
                       match=re.escape(f"grid file '{path}': ") + ".*" + re.escape(message)):
        gridio.read_header(path)


@pytest.mark.parametrize("suffix", [".vol", ".npy", ".vdb"])
@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_grid_info_refuses_a_fifo(tmp_path, suffix, json_flag):
    """Issue 46.4: ``grid info`` on a FIFO named ``.vdb`` hung forever (its grid list
    was read without the check); run in a child process so that a hang fails, not
    blocks, the suite."""
    path = tmp_path / f"pipe{suffix}"
    os.mkfifo(path)
    done = subprocess.run([sys.executable, "-m", "mitsuba_plugins.tools.cli", "grid", "info",
                           str(path), *json_flag], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done
    assert "is a FIFO (named pipe), not a regular file" in done.stderr, done.stderr


def test_oversized_header_names_the_file(tmp_path):
    path = tmp_path / "huge.vol"
    header = gridio.VOL_HEADER.pack(gridio.VOL_MAGIC, 3, 1, 1700, 1700, 1700, 1,
                                    0, 0, 0, 1, 1, 1)
    path.write_bytes(header)
    with pytest.raises(gridio.GridFileError,
                       match=f"grid file '{path}': 1700 x 1700 x 1700 x 1 = 4.913e\\+09 values"):
        gridio.read_header(path)


# -- issue 46's weak answers: each one clear line ------------------------------------------
@pytest.mark.parametrize("args, message", [
    (["render", "scenes/cornell_box.xml", "--spp", "4294967296"],
     "--spp = 4294967296 is invalid; allowed: an integer in [1, 4294967295]"),
    (["render", "scenes/cornell_box.xml", "--res", "100000"],
     "--res = 100000 is invalid; allowed: an integer in [1, 16384]"),
    (["render", "scenes/"], "scene 'scenes/' is a folder; give a scene file (.xml)"),
    (["render", "scenes/cornell_box.xml", "-i", "path_rr:max_depth=5:max_depth=6"],
     "integrator option 'max_depth' is given twice in 'path_rr:max_depth=5:max_depth=6'"),
    (["compare", "scenes/cornell_box.xml", "-i", "path_rr", "--spp", "7", "--passes", "2"],
     "--spp = 7 is invalid; allowed: a multiple of --passes (2)"),
])
def test_weak_answers_are_one_clear_line(args, message, capsys, tmp_path):
    """Before: nanobind's "Invoked with types", "Tensor(): invalid size specified",
    "scene file not found", a repeated option accepted, 6 spp rendered for 7."""
    rc = cli.main([*args, "-o", str(tmp_path / ("o.exr" if args[0] == "render" else "o"))])
    err = capsys.readouterr().err
    assert rc == 2 and message in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_grid_info_reports_every_file(tmp_path, capsys):
    """``grid info a.vdb missing.vdb b.vdb`` stopped at the missing file with a raw
    Errno and status 2; every file is reported, status 1."""
    bad = tmp_path / "a.vdb"
    bad.write_bytes(b"xx")
    rc = cli.main(["grid", "info", str(bad), str(tmp_path / "missing.vdb"),
                   str(SCENES / "data" / "fire.vdb")])
    out, err = capsys.readouterr()
    assert rc == 1
    assert "missing.vdb': file does not exist" in err and "a.vdb': not a readable" in err
    assert "2 of 3 grid file(s) invalid" in err and "temperature" in out


def test_a_truncated_vdb_says_so(tmp_path):
    raw = (SCENES / "data" / "fire.vdb").read_bytes()
    cut = tmp_path / "cut.vdb"
    cut.write_bytes(raw[:len(raw) * 9 // 10])
    with pytest.raises(gridio.GridFileError, match="truncated: a grid ends at byte"):
        gridio.read_header(cut)


def test_temperature_scale_range_says_what_is_allowed():
    with pytest.raises(Exception, match=r"'temperature_scale' = 0.0 is invalid; allowed: a "
                                        r"finite number > 0"):
        mi.load_dict({"type": "grid_medium", "filename": str(SCENES / "data" / "fire.vdb"),
                      "temperature_grid": "temperature", "temperature_scale": 0.0})
