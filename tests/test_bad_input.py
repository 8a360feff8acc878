"""Bad input at every boundary: meshes, parameters, outputs, killed writes,
no display, closed pipes. Each case asserts the error, that the message
names the offending file, flag or element, and that no partial file remains.
(Forged .pmz files: test_forged.py; cameras: test_cameras_cli.py.)"""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh

import pmjax
from pmjax._atomic import TEMP_MARK, atomic_folder, atomic_path, remove_stale_temporaries
from pmjax._cli import main
from pmjax.builders import BuildOptions, build_pm

SPOT = pmjax.default_model_path()


def run(*argv, env=None, timeout=120):
    return subprocess.run([sys.executable, "-m", "pmjax", *argv], capture_output=True, text=True,
                          env=env, timeout=timeout)


def leftovers(folder):
    return [n for n in os.listdir(folder) if TEMP_MARK in n]


@pytest.fixture(scope="module")
def spot_pm(tmp_path_factory):
    path = tmp_path_factory.mktemp("spot") / "spot.pmz"
    assert main(["build", SPOT, "-o", str(path), "-q"]) == 0
    return str(path)


# -- meshes ----------------------------------------------------------------------


def test_a_model_far_from_the_origin_is_refused_not_collapsed(tmp_path, capsys):
    mesh = trimesh.load(SPOT, process=False)
    v = np.asarray(mesh.vertices) / np.ptp(mesh.vertices, axis=0).max() * 0.02 + 1e7
    src = tmp_path / "far.ply"
    # An ASCII PLY of doubles, written out in full (exporters may round to float32).
    header = ("ply\nformat ascii 1.0\nelement vertex %d\nproperty double x\nproperty double y\n"
              "property double z\nelement face %d\nproperty list uchar int vertex_indices\nend_header\n")
    src.write_text(header % (len(v), len(mesh.faces)) + "".join("%r %r %r\n" % tuple(p) for p in v.tolist())
                   + "".join("3 %d %d %d\n" % tuple(f) for f in mesh.faces.tolist()))
    out = tmp_path / "far.pmz"
    assert main(["build", str(src), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "far.ply" in err and "Translate the model near the origin" in err
    assert not out.exists() and not leftovers(tmp_path)
    with pytest.raises(pmjax.MeshError, match="float32"):
        build_pm(v, np.asarray(mesh.faces))
    # The same shape near the origin builds.
    near = v - v.mean(axis=0)
    assert build_pm(*pmjax.clean_mesh(near, mesh.faces)[:2]).n_pcols > 0


def test_an_stl_soup_is_welded_into_the_same_mesh(tmp_path, capsys):
    mesh = trimesh.load(SPOT, process=False)
    stl = tmp_path / "spot.stl"
    mesh.export(stl)
    v, f = pmjax.read_mesh(stl)
    assert len(v) == 3 * len(f)  # a soup as stored
    cv, cf, kept, report = pmjax.load_clean_mesh(stl)
    pv, pf, _, _ = pmjax.load_clean_mesh(SPOT)
    assert len(cv) == len(pv) and len(cf) == len(pf)
    assert report.welded_vertices == len(v) - len(cv)
    assert np.array_equal(cv, v[kept])
    out = tmp_path / "spot.pmz"
    assert main(["build", str(stl), "-o", str(out), "-q"]) == 0
    assert "welded a triangle soup" in capsys.readouterr().err
    assert pmjax.read_pm(out).n_original_vertices == len(pv)


def test_a_single_triangle_builds_and_refines(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    data = build_pm(*pmjax.clean_mesh(v, np.array([[0, 1, 2]]))[:2])
    path = tmp_path / "tri.pmz"
    pmjax.save_pm(data, path)
    pm = pmjax.load(path)
    cam = pmjax.look_at([0.3, 0.3, 3.0], [0.3, 0.3, 0.0])
    for tau in (0.0, 1.0, np.inf):
        r = pmjax.refine(pm, cam, tau)
        assert int(r.n_faces) == len(r.mesh(pm)[1])
    assert int(pmjax.refine(pm, cam, 0.0).n_faces) == 1  # in view, nothing may collapse


# -- parameters ------------------------------------------------------------------


@pytest.mark.parametrize("argv, flag", [
    (["build", SPOT, "-o", "x.pmz", "--pair-distance", "nan"], "--pair-distance"),
    (["build", SPOT, "-o", "x.pmz", "--pair-distance", "inf"], "--pair-distance"),
    (["build", SPOT, "-o", "x.pmz", "--pair-distance", "-1"], "--pair-distance"),
    (["build", SPOT, "-o", "x.pmz", "--max-error", "nan"], "--max-error"),
    (["build", SPOT, "-o", "x.pmz", "--max-error", "-1"], "--max-error"),
    (["build", SPOT, "-o", "x.pmz", "--boundary-weight", "inf"], "--boundary-weight"),
    (["build", SPOT, "-o", "x.pmz", "--batch-share", "0"], "--batch-share"),
    (["build", SPOT, "-o", "x.pmz", "--target-faces", "2.5"], "--target-faces"),
    (["refine", "x.pmz", "--camera", "c.json", "-o", "o.ply", "--tau", "nan"], "--tau"),
    (["refine", "x.pmz", "--camera", "c.json", "-o", "o.ply", "--tau", "-1"], "--tau"),
    (["path", "x.pmz", "--orbit", "0"], "--orbit"),
    (["render", "x.pmz", "--orbit", "3", "-o", "o.mp4", "--fps", "0"], "--fps"),
    (["render", "x.pmz", "--orbit", "3", "-o", "o.mp4", "--fps", "-5"], "--fps"),
    (["eval", "x.pmz", "-o", "out", "--budget", "-1"], "--budget"),
    (["eval", "x.pmz", "-o", "out", "--budget", "2.5"], "--budget"),
    (["eval", "x.pmz", "-o", "out", "--size", "0", "600"], "--size"),
    (["eval", "x.pmz", "-o", "out", "--fov", "180"], "--fov"),
    (["view", "x.pmz", "--close-after", "nan"], "--close-after"),
])
def test_out_of_range_flags_are_refused_with_the_subcommand_usage(argv, flag, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2
    assert f"usage: pmjax {argv[0]}" in err and f"argument {flag}" in err and argv[argv.index(flag) + 1] in err
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("extra", [["--stored-normals"], ["--geomorph", "4"], ["--supersample", "2"]])
def test_path_refuses_fidelity_flags_without_fidelity(extra, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        main(["path", "x.pmz", "--orbit", "3", "--csv", "p.csv", *extra])
    err = capsys.readouterr().err
    assert info.value.code == 2
    assert "usage: pmjax path" in err and f"{extra[0]} shapes the --fidelity renders" in err
    assert os.listdir(tmp_path) == []


def test_a_misspelt_flag_gets_a_suggestion(capsys):
    with pytest.raises(SystemExit):
        main(["info", SPOT, "--jsn"])
    err = capsys.readouterr().err
    assert "usage: pmjax info" in err and "--jsn" in err and "did you mean --json?" in err


@pytest.mark.slow
def test_api_parameters_have_one_rule(spot_pm):
    pm = pmjax.load(spot_pm)
    cams = pmjax.standard_orbit(np.asarray(pm.vertices)[: pm.n_original_vertices], 4)
    cam = pmjax.index_camera(cams, 0)
    # tau: >= 0, inf allowed (every collapsible pcol), NaN refused, for one camera and for batches.
    coarsest = [int(pmjax.refine(pm, pmjax.index_camera(cams, i), np.inf).n_faces) for i in range(4)]
    assert list(pmjax.refine_batch(pm, cams, np.inf)["faces"]) == coarsest
    for bad in (np.nan, -1.0):
        with pytest.raises(ValueError, match="tau must be >= 0"):
            pmjax.refine(pm, cam, bad)
        with pytest.raises(ValueError, match="tau must be >= 0"):
            pmjax.refine_batch(pm, cams, bad)
    import jax.numpy as jnp
    with pytest.raises(ValueError, match="tau must be >= 0"):
        pmjax.refine(pm, cam, jnp.float32(np.nan))  # a concrete array is checked on the host
    # Budgets: whole numbers >= 0; the answer is what refine draws at that tau.
    for bad in (-1, 2.5, np.nan, "3", True):
        with pytest.raises(ValueError, match="face budget must be a whole number"):
            pmjax.faces_for_budget(pm, cam, bad)
    finest = int(pmjax.refine(pm, cam, 0.0).n_faces)
    assert finest < len(pm.faces)  # culling runs pcols even at tau 0
    assert pmjax.faces_for_budget(pm, cam, 10 ** 9) == (0.0, finest)
    for budget in (finest - 1, 500, 0):
        tau, faces = pmjax.faces_for_budget(pm, cam, budget)
        assert int(pmjax.refine(pm, cam, tau).n_faces) == faces
        assert faces <= budget or (tau == np.inf and faces == min(coarsest[0], faces))
    # Builder options: NaN, negative and infinite values named.
    for bad, name in [(dict(pair_distance=np.nan), "pair_distance"), (dict(pair_distance=np.inf), "pair_distance"),
                      (dict(max_error=np.nan), "max_error"), (dict(boundary_weight=-1.0), "boundary_weight"),
                      (dict(target_faces=1.5), "target_faces")]:
        with pytest.raises(ValueError, match=name):
            BuildOptions(**bad).validate()
    # Evaluation jobs follow the same rules (and accept tau = inf like refine_batch).
    from pmjax._eval import EvalError
    for bad in (dict(taus=[np.nan]), dict(budgets=[2.5]), dict(budgets=[-1])):
        with pytest.raises(EvalError, match="tau must be >= 0|face budget must be a whole number"):
            pmjax.evaluate([spot_pm], ["orbit:4"], "never", compile_cache=None, progress=False, **bad)
    assert not os.path.exists("never")
    from pmjax.render import render_path
    with pytest.raises(ValueError, match="fps must be"):
        render_path(pm, cams, 1.0, "never.mp4", fps=0)
    assert not os.path.exists("never.mp4")


# -- outputs ---------------------------------------------------------------------


def test_outputs_into_a_missing_folder_fail_before_any_work(spot_pm, tmp_path, capsys):
    missing = tmp_path / "no" / "such"
    t = time.perf_counter()
    assert main(["build", SPOT, "-o", str(missing / "x.pmz"), "-q"]) == 2
    assert time.perf_counter() - t < 5  # refused before building (a build takes longer)
    err = capsys.readouterr().err
    assert f"folder {tmp_path / 'no'}" in err or f"folder {missing}" in err
    cam = tmp_path / "cam.json"
    pmjax.save_cameras(pmjax.look_at([0, 0, 4.0], [0, 0, 0]), cam)
    mesh = tmp_path / "o.ply"
    assert main(["refine", spot_pm, "--camera", str(cam), "-o", str(mesh), "--stats-json",
                 str(missing / "s.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not mesh.exists()  # the mesh is not written when the stats cannot be
    assert main(["lod", spot_pm, "-o", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    for argv in (["figures", spot_pm, "-o", str(missing)], ["eval", spot_pm, "-o", str(missing)],
                 ["render", spot_pm, "--orbit", "2", "-o", str(missing / "v.gif"), "-q"],
                 ["path", spot_pm, "--orbit", "2", "--csv", str(missing / "p.csv"), "-q"]):
        assert main(argv) == 2, argv
        assert "does not exist" in capsys.readouterr().err
    assert not missing.exists() and not (tmp_path / "no").exists()


def test_a_killed_write_leaves_a_recognised_temporary_that_the_next_write_removes(tmp_path):
    target = tmp_path / "out.pmz"
    code = ("import sys, time; from pmjax._atomic import atomic_path\n"
            "with atomic_path(sys.argv[1], '.pmz') as tmp:\n"
            "    open(tmp, 'w').write('half'); print(tmp, flush=True); time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(target)], stdout=subprocess.PIPE, text=True)
    tmp = proc.stdout.readline().strip()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not target.exists()
    assert os.path.basename(tmp).startswith(".out.pmz" + TEMP_MARK + str(proc.pid) + "-")
    assert leftovers(tmp_path) == [os.path.basename(tmp)]
    # A live writer's temporary is kept; a dead one's goes on the next write.
    with atomic_path(target) as mine:
        assert remove_stale_temporaries(target) == []
        assert os.path.exists(mine) and not os.path.exists(tmp)
        open(mine, "w").write("whole")
    assert target.read_text() == "whole" and leftovers(tmp_path) == []


def test_a_file_written_over_keeps_its_permissions_and_reaches_the_disk_before_the_rename(tmp_path, monkeypatch):
    target = tmp_path / "out.txt"
    target.write_text("old")
    os.chmod(target, 0o600)
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: events.append("fsync") or real_fsync(fd))
    monkeypatch.setattr(os, "replace", lambda a, b: events.append("replace") or real_replace(a, b))
    with atomic_path(target) as tmp:
        open(tmp, "w").write("new")
    assert target.read_text() == "new" and events == ["fsync", "replace"]
    assert (os.stat(target).st_mode & 0o777) == 0o600
    # A new file gets the permissions a plain open() gives.
    umask = os.umask(0o022)
    try:
        with atomic_path(tmp_path / "fresh.txt") as tmp:
            open(tmp, "w").write("x")
    finally:
        os.umask(umask)
    assert (os.stat(tmp_path / "fresh.txt").st_mode & 0o777) == 0o644


def test_a_folder_of_files_is_assembled_inside_the_folder(tmp_path):
    """The temporary folder lies inside the target (one file system, the
    parent untouched); on an error a folder the write created goes again,
    one that existed stays with its files."""
    out = tmp_path / "frames"
    with atomic_folder(out) as tmp:
        assert os.path.dirname(tmp) == str(out) and os.listdir(tmp_path) == ["frames"]
        open(os.path.join(tmp, "a.png"), "w").write("a")
    assert sorted(os.listdir(out)) == ["a.png"] and os.listdir(tmp_path) == ["frames"]
    with pytest.raises(RuntimeError):
        with atomic_folder(tmp_path / "new") as tmp:
            open(os.path.join(tmp, "b.png"), "w").write("b")
            raise RuntimeError("stop")
    assert os.listdir(tmp_path) == ["frames"]
    with pytest.raises(RuntimeError):
        with atomic_folder(out) as tmp:
            open(os.path.join(tmp, "b.png"), "w").write("b")
            raise RuntimeError("stop")
    assert sorted(os.listdir(out)) == ["a.png"]


@pytest.mark.slow
def test_kill_during_build_never_leaves_a_partial_pm(tmp_path, data_path):
    out = tmp_path / "bunny.pmz"
    proc = subprocess.Popen([sys.executable, "-m", "pmjax", "build", data_path("bunny.ply"), "-o", str(out), "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not leftovers(tmp_path) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.005)
    proc.kill()
    proc.wait()
    assert not out.exists() or pmjax.read_pm(out).n_pcols > 0  # absent, or whole
    assert main(["build", data_path("cow.ply"), "-o", str(out), "-q"]) == 0
    assert leftovers(tmp_path) == []
    pmjax.read_pm(out)


# -- environment -----------------------------------------------------------------


@pytest.mark.slow
def test_view_without_a_display_exits_with_a_message(spot_pm):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = run("view", spot_pm, "--close-after", "1", env=env, timeout=60)
    assert r.returncode == 2 and "needs a display" in r.stderr and "xvfb-run" in r.stderr
    r = run("view", spot_pm, "--close-after", "1", env=dict(env, DISPLAY=":7777"), timeout=60)
    assert r.returncode == 2 and "cannot open the display ':7777'" in r.stderr
    assert "Traceback" not in r.stderr


def test_a_closed_pipe_is_quiet(spot_pm):
    r = subprocess.run(f"{sys.executable} -m pmjax info {spot_pm} | head -1", shell=True, capture_output=True,
                       text=True, timeout=60)
    assert r.stdout.startswith(spot_pm) and r.stderr == ""
