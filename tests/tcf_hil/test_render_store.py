"""The render store: frames rendered ahead and kept under a key made of everything that decides
their bytes; a run that sends a stored render writes the very files a live render writes, on
any ports; a render cut short keeps its whole frames and resumes; the cache stays under its
size limit."""

from __future__ import annotations

import functools
import os
import socket
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.lidar import Datagram
from tcf_hil.devices.lidar import LidarRun
from tcf_hil.devices.offline import record_pcap
from tcf_hil.errors import ConfigError
from tcf_hil.recording.store import RenderedFrame, RenderStore, render_key
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict

SIDECARS = ("lidar.pcap", "lidar_labels.bin", "sensor_poses.csv", "ground_truth.json",
            "visibility.json", "metadata.json")


def _short(faults: bool = False):  # type: ignore[no-untyped-def]
    d = scenario_to_dict(load_scenario("forest-ii"))
    if faults:  # every kind of event a frame may carry, and a re-initialisation
        d["faults"] = {"udp": {"loss": 0.02, "duplicate": 0.02, "reorder": 0.02},
                       "lidar": {"dropout_at_s": [0.3], "reinit_at_s": [0.6],
                                 "reinit_gap_s": 0.2}}
    return scenario_from_dict(d)


def _tiny(name: str):  # type: ignore[no-untyped-def]
    """``name`` with a track of 2 m (about 30 frames at 10 Hz): a whole render in seconds."""
    d = scenario_to_dict(load_scenario(name))
    d["track"]["end_m"] = [d["track"]["start_m"][0], d["track"]["start_m"][1] + 2.0,
                           d["track"]["start_m"][2]]
    return scenario_from_dict(d)


def _blocks():  # type: ignore[no-untyped-def]
    """forest-ii driven 2 s and stopped: 20 frames and more, a few render blocks."""
    d = scenario_to_dict(load_scenario("forest-ii"))
    d["track"].update(end_m=[0.0, -21.0, 2.0], speed_m_s=2.0)
    return scenario_from_dict(d)


def _files(d: Path) -> dict[str, bytes]:
    return {n: (d / n).read_bytes() for n in SIDECARS if (d / n).exists()}


@pytest.mark.slow  # the second lane: whole tracks rendered, runs
@pytest.mark.parametrize("faults", [False, True])
def test_a_stored_render_sends_the_bytes_a_live_render_sends(tmp_path: Path,
                                                             faults: bool) -> None:
    scn = _short(faults)
    store = RenderStore(tmp_path / "cache")
    kw = {"mode": "512x10", "max_frames": 12}
    live = record_pcap(scn, tmp_path / "live", **kw)
    # rendered into the store first (whole track), then sent from it, on other ports
    stored = record_pcap(scn, tmp_path / "stored", store=store, render="stored", **kw)
    assert store.entries() and store.entries()[0]["complete"]
    a, b = _files(tmp_path / "live"), _files(tmp_path / "stored")
    assert a.keys() == b.keys() and "lidar.pcap" in a
    for name in a:
        assert a[name] == b[name], name
    assert (live.frames, live.packets, live.returns) == (stored.frames, stored.packets,
                                                         stored.returns)
    # the same render serves another run on other ports: the ports follow the run
    other = LidarRun(scn, mode="512x10", max_frames=12, store=store, render="auto",
                     udp_port_lidar=41000, udp_port_imu=41001)
    assert other.stored is not None
    ports = {d.port for rf in other.rendered() for d in rf.datagrams}
    assert ports <= {41000, 41001} and 41000 in ports
    other.stored.close()


def test_auto_renders_live_where_nothing_is_stored(tmp_path: Path) -> None:
    store = RenderStore(tmp_path / "cache")
    run = LidarRun(_short(), mode="512x10", max_frames=3, store=store, render="auto")
    assert run.stored is None
    assert len(list(run.rendered())) == 3
    assert store.entries() == []  # auto never fills the store by itself


def test_the_key_follows_what_decides_the_bytes(tmp_path: Path) -> None:
    scn = _short()
    k = LidarRun(scn, mode="512x10").render_key
    assert k == LidarRun(scn, mode="512x10", udp_port_lidar=40000, max_frames=5).render_key
    assert k != LidarRun(scn, mode="1024x10").render_key
    assert k != LidarRun(scn, mode="512x10", seed=scn.seed + 1).render_key
    assert k != LidarRun(_short(faults=True), mode="512x10").render_key
    # faults off (an offline cell) or on (a run) render a scene without fault plans alike
    assert k == LidarRun(scn, mode="512x10", faults=False).render_key
    assert (LidarRun(_short(faults=True), mode="512x10", faults=False).render_key
            == k)
    assert render_key({"a": 1}) != render_key({"a": 2})


def test_a_hand_built_forest_is_never_stored(tmp_path: Path) -> None:
    scn = _short()
    forest = LidarRun(scn, mode="512x10").forest
    assert LidarRun(scn, mode="512x10", forest=forest).render_key is None
    with pytest.raises(ConfigError, match="render"):
        LidarRun(scn, mode="512x10", forest=forest, store=RenderStore(tmp_path),
                 render="stored")
    with pytest.raises(ConfigError, match="render"):
        LidarRun(scn, mode="512x10", render="sometimes")


@pytest.mark.slow  # the second lane: whole tracks rendered, runs
def test_a_render_cut_short_resumes_after_its_last_whole_frame(tmp_path: Path) -> None:
    scn = _short()
    store = RenderStore(tmp_path / "cache")
    whole = LidarRun(scn, mode="512x10", store=store, render="stored")
    whole.render_into_store()
    key = whole.render_key
    assert key is not None
    ref = (store.path(key) / "frames.bin").read_bytes()
    idx = (store.path(key) / "frames.idx").read_bytes()
    n = len(idx) // 8
    # cut short: 5 frames indexed, half of the sixth written, not complete
    store.remove(key)
    p = store.path(key)
    cut = int(np.frombuffer(idx, "<u8")[5])  # (where the sixth record starts)
    w = store.writer(key, {"x": 1}, n)
    assert w is not None
    w.close()
    (p / "frames.bin").write_bytes(ref[:cut + 100])
    (p / "frames.idx").write_bytes(idx[:40])
    assert store.open(key) is None  # never streamed: not complete
    assert not store.entries()[0]["complete"] and store.entries()[0]["frames"] == 5
    again = LidarRun(scn, mode="512x10", store=store, render="stored")
    assert again.render_into_store() == n - 5
    assert (p / "frames.bin").read_bytes() == ref
    assert again.stored is not None and again.stored.complete


def test_a_render_by_two_workers_is_the_render_in_order(tmp_path: Path) -> None:
    scn = _blocks()  # 2 s and a stop: 20 frames and more, in blocks
    one, two = RenderStore(tmp_path / "one"), RenderStore(tmp_path / "two")
    a = LidarRun(scn, mode="512x10", store=one, render="stored")
    a.render_into_store(workers=1)
    b = LidarRun(scn, mode="512x10", store=two, render="stored")
    seen: list[int] = []
    assert b.render_into_store(progress=lambda k, n: seen.append(k), workers=2) \
        == a.track_frames >= 20
    assert seen == list(range(1, a.track_frames + 1))  # in order, whoever made them
    key = a.render_key
    assert key is not None and key == b.render_key
    for name in ("frames.bin", "frames.idx"):
        assert (one.path(key) / name).read_bytes() == (two.path(key) / name).read_bytes()
    # cut short after 7 frames (mid block), then resumed by two workers: the same bytes
    idx = (two.path(key) / "frames.idx").read_bytes()
    ref = (two.path(key) / "frames.bin").read_bytes()
    two.remove(key)
    w = two.writer(key, {"x": 1}, a.track_frames)
    assert w is not None
    w.close()
    (two.path(key) / "frames.bin").write_bytes(ref[:int(np.frombuffer(idx, "<u8")[7])])
    (two.path(key) / "frames.idx").write_bytes(idx[:56])
    again = LidarRun(scn, mode="512x10", store=two, render="stored")
    assert again.render_into_store(workers=2) == a.track_frames - 7
    assert (two.path(key) / "frames.bin").read_bytes() == ref
    assert again.stored is not None and again.stored.complete


def test_a_head_start_by_two_workers_then_one_renderer_is_the_render_in_order(
        tmp_path: Path) -> None:
    """A live run with nothing stored renders its first frames with every core before the
    program starts (``render_head``, until ``enough``), then one renderer of its own carries
    on from there (``render_ahead``): the store holds the one-process render's bytes."""
    scn = _blocks()
    one, two = RenderStore(tmp_path / "one"), RenderStore(tmp_path / "two")
    a = LidarRun(scn, mode="512x10", store=one, render="stored")
    a.render_into_store(workers=1)
    b = LidarRun(scn, mode="512x10", store=two, render="auto")
    assert b.stored is None and b.frames == a.track_frames >= 20
    asked: list[tuple[int, float]] = []

    def enough(d: int, rate: float) -> bool:
        asked.append((d, rate))
        return d >= 12

    assert b.render_head(enough, workers=2) == 12  # (mid block: the workers stop at once)
    assert [d for d, _ in asked] == list(range(1, 13)) and all(r > 0 for _, r in asked)
    assert not two.entries()[0]["complete"] and two.entries()[0]["frames"] == 12
    ahead = b.render_ahead()
    assert ahead is not None
    ahead.process.join(120)
    assert ahead.state.value == 1 and int(ahead.done.value) == a.track_frames
    key = a.render_key
    assert key is not None and key == b.render_key
    for name in ("frames.bin", "frames.idx"):
        assert (one.path(key) / name).read_bytes() == (two.path(key) / name).read_bytes()
    assert b.stored is not None
    b.stored.close()
    # nothing to start where the render is complete, or with one worker
    c = LidarRun(scn, mode="512x10", store=two, render="auto")
    assert c.render_head(enough, workers=2) == 0
    d = LidarRun(scn, mode="512x10", store=RenderStore(tmp_path / "three"), render="auto")
    assert d.render_head(enough, workers=1) == 0


def test_a_pcap_by_two_renderers_is_the_pcap_in_order(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """``tcf-hil lidar pcap``'s default on a machine of several CPUs: blocks of frames made
    by renderer processes at once, written in order: every file the bytes one process
    writes (a stop mid-block included)."""
    forked: list[int] = []
    parallel = LidarRun._render_parallel

    def spy(self, *a, **kw):  # type: ignore[no-untyped-def]
        forked.append(a[1])  # the workers, and then the real thing
        return parallel(self, *a, **kw)

    monkeypatch.setattr(LidarRun, "_render_parallel", spy)
    scn = _blocks()
    kw = {"mode": "512x10", "max_frames": 15}  # a block and a half
    seen: list[int] = []
    one = record_pcap(scn, tmp_path / "one", workers=1, **kw)
    two = record_pcap(scn, tmp_path / "two", workers=2, progress=lambda k, n: seen.append(k),
                      **kw)
    assert seen == list(range(1, 16)) and one.frames == 15 and forked == [2]
    a, b = _files(tmp_path / "one"), _files(tmp_path / "two")
    assert a.keys() == b.keys() == set(SIDECARS)
    for name in a:
        assert a[name] == b[name], name
    assert (one.frames, one.packets, one.returns, one.stems_seen) == \
        (two.frames, two.packets, two.returns, two.stems_seen)


@pytest.mark.slow  # the second lane (.ci/run): out of the fast lane's ten minutes
def test_a_render_by_dask_workers_is_the_render_in_order(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Blocks of frames rendered by a running Dask scheduler's worker processes (each builds
    the scene from the render's recipe) are stored in order, byte for byte the render made
    here; the CLI names a scheduler that does not answer."""
    from dask.distributed import LocalCluster

    from tcf_hil.cli import main
    from tcf_hil.devices.dask_render import render_on_dask

    scn = _blocks()
    here, there = RenderStore(tmp_path / "here"), RenderStore(tmp_path / "there")
    a = LidarRun(scn, mode="512x10", store=here, render="stored")
    a.render_into_store(workers=1)
    b = LidarRun(scn, mode="512x10", store=there, render="stored")
    seen: list[int] = []
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        remote = functools.partial(render_on_dask, address=cluster.scheduler_address)
        assert b.render_into_store(progress=lambda k, n: seen.append(k), remote=remote) \
            == a.track_frames
    assert seen == list(range(1, a.track_frames + 1))
    key = a.render_key
    assert key is not None and key == b.render_key and b.stored is not None
    for name in ("frames.bin", "frames.idx"):
        assert (here.path(key) / name).read_bytes() == (there.path(key) / name).read_bytes()
    monkeypatch.setenv("TCF_HIL_CACHE", str(tmp_path / "cli"))
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        code = main(["render", "forest-ii", "--mode", "512x10",
                     "--executor", f"dask://127.0.0.1:{port}"])
    said = capsys.readouterr()
    assert code != 0 and f"127.0.0.1:{port}" in said.out + said.err
    assert main(["render", "forest-ii", "--executor", "inline"]) == 2
    said = capsys.readouterr()
    assert "--executor" in said.out + said.err
    # fault plans render in order, here; --workers is the local executor's
    assert main(["render", "forest-ii", "--mode", "512x10", "--fault", "udp.loss=0.01",
                 "--executor", f"dask://127.0.0.1:{port}"]) == 2
    said = capsys.readouterr()
    assert "fault plans" in said.out + said.err
    assert main(["render", "forest-ii", "--mode", "512x10", "--workers", "2",
                 "--executor", f"dask://127.0.0.1:{port}"]) == 2


def test_a_worker_that_would_make_another_render_refuses_its_block() -> None:
    """A worker builds the run from the recipe; where that makes another key (other code,
    another backend), it says so instead of storing other bytes under the key."""
    from tcf_hil.devices.dask_render import recipe, render_block

    run = LidarRun(_tiny("forest-ii"), mode="512x10")
    spec = recipe(run)
    assert [k for k, _ in render_block(spec, 2, 4)] == [2, 3]
    with pytest.raises(RuntimeError, match="differs from the client's"):
        render_block({**spec, "key": "0" * 24}, 0, 1)


def test_the_cache_keeps_under_its_limit_least_recently_used_first(tmp_path: Path) -> None:
    store = RenderStore(tmp_path, max_gb=1e-9 * 250)  # 250 bytes
    for i, key in enumerate(("a", "b", "c")):
        w = store.writer(key, {"i": i}, 1)
        assert w is not None
        w.append(RenderedFrame(0, [Datagram(1, 7502, b"x" * 60)], b"", b"", np.zeros(0, np.int64),
                               np.zeros(0, np.int64), [], "send", 1), (7502, 7503))
        w.complete()
        w.close()
        os.utime(store.path(key) / "render.json", (1000 + i, 1000 + i))
    keys = [e["key"] for e in store.entries()]
    assert keys[0] == "c" and set(keys) <= {"a", "b", "c"}
    assert store.size() <= 250 + max(e["bytes"] for e in store.entries())
    gone = store.evict(room=10_000)
    assert gone and "c" not in gone[:-1]
    n, size = store.clear()
    assert store.entries() == [] and n >= 0 and size >= 0


def test_a_bad_size_limit_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tcf_hil.errors import InputError

    monkeypatch.setenv("TCF_HIL_CACHE_MAX_GB", "lots")
    with pytest.raises(InputError, match="TCF_HIL_CACHE_MAX_GB"):
        RenderStore(tmp_path)


_dg = st.builds(Datagram, st.integers(0, 2**62), st.sampled_from([7502, 7503, 9000]),
                st.binary(max_size=64))


@settings(max_examples=60, deadline=None)
@given(k=st.integers(0, 10**6), dgs=st.lists(_dg, max_size=6), labels=st.binary(max_size=40),
       poses=st.binary(max_size=40),
       hits=st.lists(st.tuples(st.integers(-1, 2**40), st.integers(0, 2**40)), max_size=5),
       events=st.lists(st.fixed_dictionaries({"kind": st.sampled_from(["udp_loss", "x"]),
                                              "frame": st.integers(0, 99)}), max_size=3),
       action=st.sampled_from(["send", "drop", "reinit", "silent"]),
       init_id=st.integers(0, 2**24 - 1))
def test_a_frame_record_reads_back_as_written(k, dgs, labels, poses, hits, events, action,
                                              init_id) -> None:  # type: ignore[no-untyped-def]
    ids = np.array([h[0] for h in hits], np.int64)
    counts = np.array([h[1] for h in hits], np.int64)
    rf = RenderedFrame(k, dgs, labels, poses, ids, counts, events, action, init_id)
    rec = b"junk" + rf.encode((7502, 7503)) + b"tail"
    back, end = RenderedFrame.decode(rec, 4, ports=(7502, 7503))
    assert end == len(rec) - 4
    assert (back.k, back.labels, back.poses, back.events, back.action, back.init_id) == (
        k, labels, poses, events, action, init_id)
    assert back.hit_ids.tolist() == ids.tolist() and back.hit_counts.tolist() == counts.tolist()
    assert [(d.t_ns, d.port, bytes(d.payload)) for d in back.datagrams] == [
        (d.t_ns, d.port, bytes(d.payload)) for d in dgs]
    # on other ports: the lidar and IMU datagrams follow, any other keeps its port
    moved, _ = RenderedFrame.decode(rec, 4, ports=(41000, 41001))
    assert [d.port for d in moved.datagrams] == [
        {7502: 41000, 7503: 41001}.get(d.port, d.port) for d in dgs]


def test_a_damaged_stored_record_is_named(tmp_path: Path) -> None:
    from tcf_hil.errors import InputError

    store = RenderStore(tmp_path)
    w = store.writer("k", {}, 1)
    assert w is not None
    w.append(RenderedFrame(0, [Datagram(1, 7502, b"abc" * 50)], b"", b"",
                           np.zeros(0, np.int64), np.zeros(0, np.int64), [], "send", 1),
             (7502, 7503))
    w.complete()
    w.close()
    raw = bytearray((store.path("k") / "frames.bin").read_bytes())
    raw[10] ^= 0xFF
    (store.path("k") / "frames.bin").write_bytes(bytes(raw))
    r = store.open("k")
    assert r is not None
    with pytest.raises(InputError, match=r"frames\.bin.*damaged"):
        r.frame(0)
    r.close()


def test_a_truncated_record_is_named(tmp_path: Path) -> None:
    from tcf_hil.errors import InputError

    rf = RenderedFrame(0, [Datagram(1, 7502, b"abc")], b"", b"", np.zeros(0, np.int64),
                       np.zeros(0, np.int64), [], "send", 1)
    rec = rf.encode((7502, 7503))
    with pytest.raises(InputError, match="truncated"):
        RenderedFrame.decode(rec[:-2], 0, "x/frames.bin")
    with pytest.raises(InputError, match="not a frame record"):
        RenderedFrame.decode(b"XXXX" + rec[4:], 0)


@pytest.mark.slow  # the second lane: whole tracks rendered, runs
def test_render_then_run_streams_the_stored_bytes_as_a_user_types_it(tmp_path: Path) -> None:
    """``tcf-hil render``, ``cache list``, then two runs of the same scenario and seed: one
    streamed from the store, one rendered live. Both recordings hold the very same lidar
    bytes (the track is stamped on the run's fixed simulation time line); ``cache clear``
    frees the store."""
    import json
    import subprocess
    import sys

    env = dict(os.environ, TCF_HIL_CACHE=str(tmp_path / "cache"), COLUMNS="200")
    tcf = [sys.executable, "-m", "tcf_hil.cli"]
    scene = ["forest-ii", "--mode", "512x10", "--sensor", "ideal"]

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*tcf, *args], capture_output=True, text=True, env=env,
                              timeout=600)

    p = cli("render", *scene)
    assert p.returncode == 0 and "frames rendered" in p.stdout, p.stdout + p.stderr
    p = cli("render", *scene)
    assert p.returncode == 0 and "already stored" in p.stdout, p.stdout + p.stderr
    p = cli("cache", "list")
    assert p.returncode == 0 and "forest-ii" in p.stdout and "512x10" in p.stdout, p.stdout
    sic = ("{python} -c \"import sys, time; print('{\\\"objects\\\": []}', flush=True); "
           "time.sleep(60)\"")
    runs = {}
    for render in ("auto", "live"):
        out = tmp_path / render
        p = cli("run", *scene, "--duration", "2", "--grace", "1", "--ready-timeout", "0",
                "--render", render, "--sic", sic, "--out", str(out))
        man = json.loads((out / "manifest.json").read_text())
        assert man["lidar"]["render"]["from_store"] == (render == "auto"), p.stdout + p.stderr
        assert man["lidar"]["frames_sent"] == 20
        steal = man["lidar"]["track_steal_ms_per_s"]  # /proc/stat's steal over the track
        assert steal is None or 0.0 <= steal <= 2000.0  # both CPUs: at most 2 s a second
        machine = man["lidar"]["machine"]  # what decides the sender's wake-ups here
        assert machine["cpus"] >= 1 and machine["kernel"] and "hypervisor" in machine
        runs[render] = out
    for name in ("lidar.pcap", "lidar_labels.bin", "sensor_poses.csv"):
        assert (runs["auto"] / name).read_bytes() == (runs["live"] / name).read_bytes(), name
    p = cli("cache", "clear")
    assert p.returncode == 0 and "freed 1 renders" in p.stdout, p.stdout
    assert "empty" in cli("cache", "list").stdout
    p = cli("cache", "clear", "--key", "nosuchkey")
    assert p.returncode == 2 and "no such render" in p.stderr


def test_experiment_cells_that_differ_only_in_the_sic_share_one_render(tmp_path: Path) -> None:
    """``fill``: the first offline run of a scene renders and keeps its frames, the next
    (another preset of the reference SIC) reads them, and gets what a live render gives."""
    from tcf_hil.experiments.offline import run_offline

    d = scenario_to_dict(load_scenario("forest-ii"))
    d["track"]["end_m"] = [0.0, -20.0, 2.0]  # 5 m: a short track
    scn = scenario_from_dict(d)
    os.environ["TCF_HIL_CACHE"], old = str(tmp_path / "cache"), os.environ["TCF_HIL_CACHE"]
    try:
        first = run_offline(scn, mode="512x10", preset="tuned", render="fill")
        second = run_offline(scn, mode="512x10", preset="paper", render="fill")
        again = run_offline(scn, mode="512x10", preset="paper", render="live")
    finally:
        os.environ["TCF_HIL_CACHE"] = old
    assert not first.from_store and second.from_store and not again.from_store
    assert second.forest_doc["objects"] == again.forest_doc["objects"]
    assert second.frames == again.frames and second.packets == again.packets
    assert second.ground_truth == again.ground_truth
    assert len(RenderStore(tmp_path / "cache").entries()) == 1


def test_one_writer_per_render(tmp_path: Path) -> None:
    store = RenderStore(tmp_path)
    w = store.writer("k", {}, 1)
    assert w is not None
    assert store.writer("k", {}, 1, wait=False) is None  # another writes it
    w.close()
    w2 = store.writer("k", {}, 1, wait=False)
    assert w2 is not None
    w2.close()


def _frame_ids_and_times(run: LidarRun, frames: list[tuple[str, RenderedFrame]]
                         ) -> list[tuple[str, int, int]]:
    from protocols.ouster import decode_lidar_packet

    fmt, lp = run.meta.packet_format, run.ports[0]
    out = []
    for phase, rf in frames:
        ps = [decode_lidar_packet(fmt, bytes(d.payload), init_id=run.meta.init_id,
                                  prod_sn=run.meta.prod_sn) for d in rf.datagrams
              if d.port == lp]  # (the CRC is checked: a restamped packet must carry its own)
        assert len({p.frame_id for p in ps}) == 1
        out.append((phase, ps[0].frame_id, int(ps[0].timestamps_ns.min())))
    return out


def test_an_always_on_sensor_stands_steps_drives_and_stands(tmp_path: Path) -> None:
    """The frames an always-on sensor sends (:meth:`LidarRun.on_air`): standing on the
    power-on time line, then (after the run's decision) on the track's, the track as a run
    without standing frames sends it but for frame_id and CRC, then standing on; frame_id
    counts on by one throughout, the IMU every 10 ms with no burst at the step."""
    import itertools
    import multiprocessing as mp

    from tcf_hil.devices.lidar import OnAir

    scn = _short()
    run = LidarRun(scn, mode="512x10", max_frames=6, t0_ns=60_000_000_000)
    period, t0 = run.emu.period_ns, run.track.t0_ns
    air = OnAir(t0 - 50 * period, mp.RawValue("q", -1), mp.RawValue("q", -1))
    gen = run.on_air(air, run.standing(t0 - period), run.standing(t0 + 6 * period))
    first = list(itertools.islice(gen, 10))
    air.step_at.value, air.track_at.value = 10, 14  # decided after ten frames
    rest = list(itertools.islice(gen, 4 + 6 + 3))
    seq = _frame_ids_and_times(run, first + rest)
    assert [p for p, _, _ in seq] == ["unheard"] * 10 + ["before"] * 4 + ["track"] * 6 + [
        "after"] * 3
    assert [i for _, i, _ in seq] == list(range(23))
    times = [t for _, _, t in seq]
    assert times[0] == t0 - 50 * period and times[13] == t0 - period and times[14] == t0
    assert all(b - a == period for a, b in itertools.pairwise(times[10:]))
    assert times[10] - times[9] == (50 - 14) * period + period  # the one step forward
    # the track: the bytes of the same frames with no standing before them, but frame_id
    plain = LidarRun(scn, mode="512x10", max_frames=6, t0_ns=60_000_000_000)
    ref = list(plain.rendered())
    from protocols.ouster import shift_lidar_packet
    from tcf_hil._crc import fast_crc_rows

    fmt, crc = run.meta.packet_format, fast_crc_rows()
    for (_, rf), rr in zip(rest[4:10], ref, strict=True):
        assert [(d.t_ns, d.port, shift_lidar_packet(fmt, bytes(e.payload), 14, 0, crc)
                 if e.port == run.ports[0] else bytes(e.payload)) for d, e in
                zip(rf.datagrams, rr.datagrams, strict=True)] == [
            (d.t_ns, d.port, bytes(d.payload)) for d in rf.datagrams]
    imu = [d.t_ns for _, rf in first + rest for d in rf.datagrams if d.port == run.ports[1]]
    gaps = sorted({b - a for a, b in itertools.pairwise(imu)})
    assert gaps[0] == 10_000_000 and len(gaps) == 2  # 100 Hz, and the step once


def test_a_standing_cycle_kept_in_the_store_is_the_one_rendered(tmp_path: Path) -> None:
    """The standing machine's frames (rendered at every run's start, seconds on a natural
    stand) are kept beside the track's complete render and read back bit for bit; a file
    that cannot be read is rendered again; without a complete render nothing is kept."""
    scn = _tiny("forest-ii")
    store = RenderStore(tmp_path / "cache")
    kw = {"mode": "512x10", "max_frames": 4}
    run = LidarRun(scn, store=store, render="stored", **kw)
    at = run.track.t0_ns - run.emu.period_ns
    assert run._cycle_path(at) is None  # nothing stored yet: nothing kept
    run.render_into_store()
    first = run.standing(at)
    path = run._cycle_path(at)
    assert path is not None and path.exists()
    again = LidarRun(scn, store=store, render="stored", **kw)
    kept = again.standing(at)
    plain = LidarRun(scn, **kw).standing(at)  # no store: rendered
    for k in (0, 3, 17):
        a, b, c = first.frame(k), kept.frame(k), plain.frame(k)
        for f in ("packets", "timestamps_ns", "stem_id", "positions", "rotations"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
            np.testing.assert_array_equal(getattr(a, f), getattr(c, f), err_msg=f)
        assert b.field_names == c.field_names and b.packet_format == c.packet_format
    path.write_bytes(b"not an npz")
    third = LidarRun(scn, store=store, render="stored", **kw)
    np.testing.assert_array_equal(third.standing(at).frame(0).packets, plain.frame(0).packets)
    for r in (run, again, third):
        if r.stored is not None:
            r.stored.close()


@pytest.mark.parametrize("name", ["forest-ii", "forest-ii-natural"])
def test_a_run_streamed_from_a_complete_render_builds_no_scene(tmp_path: Path,
                                                               name: str) -> None:
    """A run whose frames, standing machine, labels header and scene facts are all in the
    store sends, keeps its bookkeeping and writes its sidecars without building the scene
    (seconds for a natural stand: the command's time to the first packet), and writes what
    a run that built it writes."""
    scn = _tiny(name)
    store = RenderStore(tmp_path / "cache")
    kw = {"mode": "512x10", "max_frames": 4}
    first = LidarRun(scn, store=store, render="stored", **kw)
    first.render_into_store()
    at = first.track.t0_ns - first.period_ns
    first.standing(at)
    list(first.rendered())
    head = first.labels_header()
    first.write_sidecars(tmp_path / "a")
    run = LidarRun(scn, store=store, render="stored", **kw)
    assert not run.renders and run.backend == first.scene.backend
    run.standing(at)
    list(run.rendered())
    assert run.labels_header() == head
    run.write_sidecars(tmp_path / "b")
    assert not run.renders  # nothing above built the scene
    for f in ("visibility.json", "ground_truth.json", "sensor_poses.csv"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    for r in (first, run):
        assert r.stored is not None
        r.stored.close()


def test_a_renderer_that_dies_is_named_with_its_exit_code(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    """A renderer process that ends mid-render without its end mark (killed, crashed): the
    render fails naming it and its exit code, and no renderer is left behind."""
    compact = LidarRun.compact_frames

    def dying(self, a, b):  # type: ignore[no-untyped-def]
        for rf in compact(self, a, b):
            yield rf
            if a >= 10:  # the second renderer, after its first frame
                os._exit(3)

    monkeypatch.setattr(LidarRun, "compact_frames", dying)
    run = LidarRun(_blocks(), mode="512x10", max_frames=20)
    frames = run._render_parallel(0, 2, 20, compress=False)
    got = []
    with pytest.raises(RuntimeError, match=r"render worker 1 died \(exit code 3\)"):
        for k, _ in frames:
            got.append(k)
    assert got == list(range(len(got))) and len(got) < 20  # in order, up to the failure
    import multiprocessing as mp
    assert not [p for p in mp.active_children() if p.name.startswith("lidar-render")]


def test_the_frame_pipe_carries_pieces_and_refuses_what_is_no_frame() -> None:
    """A frame crosses the renderers' pipe as its pieces (bytes, views of rows, more pieces
    than one writev takes) and reads back as one buffer; a header that claims more than a
    frame, or an end mid-message, is the end of that renderer."""
    import threading

    from tcf_hil.devices import _renderers as pipe

    rows = np.arange(3000 * 4, dtype=np.uint32).reshape(3000, 4)
    parts: list[object] = [b"head", bytearray(b"mid"), b"", *(memoryview(r) for r in rows)]
    want = b"head" + b"mid" + rows.tobytes()
    r, w = os.pipe()
    try:
        t = threading.Thread(target=pipe.send_frame, args=(w, 7, parts))
        t.start()
        k, got = pipe.recv_frame(r)
        t.join()
        assert k == 7 and bytes(got) == want
        os.write(w, pipe.FRAME_HEAD.pack(8, 1 << 40))  # no frame is a terabyte
        with pytest.raises(EOFError, match="not a frame"):
            pipe.recv_frame(r)
        os.write(w, pipe.FRAME_HEAD.pack(9, 100) + bytes(10))
        os.close(w)
        w = -1
        with pytest.raises(EOFError, match="10 of 100 bytes"):
            pipe.recv_frame(r)
    finally:
        os.close(r)
        if w >= 0:
            os.close(w)
