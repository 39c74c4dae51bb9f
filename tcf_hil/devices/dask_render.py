"""A track rendered into the render store by a Dask cluster's workers (``tcf-hil render
--executor dask://HOST:PORT``): for a scene too large for this machine's cores.

The frames are cut into blocks of :data:`~tcf_hil.devices._renderers.RENDER_BLOCK`, one task
each. A worker builds the run from the render's recipe (the scenario as a document, the
seed, mode, profile, backend: what :meth:`~tcf_hil.devices.lidar.LidarRun.render_doc`
holds) once, keeps it for the next blocks of the same render, checks that it makes the
render of the very key asked for (a worker with other code would make other bytes: it is
refused, by name), and returns the block's frames packed as the store keeps them. Here the
blocks are taken as they come and written in order; a few blocks a worker are in flight at
once, so the results held here stay bounded. Only renders without fault plans (whose bytes
follow from each frame's index) go out in blocks.
"""

from __future__ import annotations

import threading
from collections.abc import Generator, Iterator
from typing import Any

from emulators.lidar import ReturnModel
from tcf_hil.devices._renderers import RENDER_BLOCK
from tcf_hil.devices.lidar import LidarRun
from tcf_hil.errors import EndpointError
from tcf_hil.scenario import scenario_from_dict

BLOCKS_PER_WORKER = 3  # in flight at once: one rendering, one queued, one coming back

_LOCK = threading.Lock()
_KEPT: dict[str, Any] = {}  # a worker's last run, by render key (one scene in memory)


def recipe(run: Any) -> dict[str, Any]:
    """What a worker needs to build ``run`` again (plain data: it travels by pickle)."""
    doc = run.render_doc()
    if doc is None:
        raise ValueError("a forest built by the caller cannot be rendered elsewhere")
    return {"key": run.render_key, "scenario": doc["scenario"], "seed": doc["seed"],
            "backend": doc["backend"], "t0_ns": doc["t0_ns"],
            "first_frame_id": doc["first_frame_id"], "faults": doc["faults"],
            "model": doc["model"], "mode": run.meta.mode, "profile": run.meta.profile,
            "ports": list(run.ports)}


def _run_for(spec: dict[str, Any]) -> Any:
    key = spec["key"]
    with _LOCK:
        run = _KEPT.get(key)
        if run is None:
            model = ReturnModel(**spec["model"]) if spec["model"] is not None else None
            run = LidarRun(scenario_from_dict(spec["scenario"]), mode=spec["mode"],
                           profile=spec["profile"], seed=spec["seed"],
                           backend=spec["backend"], model=model, t0_ns=spec["t0_ns"],
                           faults=spec["faults"], first_frame_id=spec["first_frame_id"],
                           udp_port_lidar=spec["ports"][0], udp_port_imu=spec["ports"][1])
            if run.render_key != key:
                raise RuntimeError(f"this worker makes render {run.render_key}, not {key}: "
                                   "its tcf-hil (or its backend) differs from the client's")
            _KEPT.clear()
            _KEPT[key] = run
        return run


def render_block(spec: dict[str, Any], a: int, b: int) -> list[tuple[int, bytes]]:
    """Frames ``a`` .. ``b`` - 1 of the render ``spec`` (:func:`recipe`), packed: a task."""
    run = _run_for(spec)
    with _LOCK:  # one block at a time in a worker process (the run keeps a frame's state)
        return list(run.packed_frames(a, b))


def render_on_dask(run: Any, start: int, address: str
                   ) -> Generator[tuple[int, bytes], None, None]:
    """Frames ``start`` .. of ``run``'s track, packed, in order, from the workers of the Dask
    scheduler at ``address`` (``tcp://HOST:PORT``): ``render_into_store``'s ``remote``."""
    from dask.distributed import Client, as_completed

    spec = recipe(run)
    n = run.track_frames
    cuts = list(range(start, n, RENDER_BLOCK))
    try:
        client = Client(address, timeout="10s")
    except OSError as err:
        raise EndpointError(f"--executor: no Dask scheduler answers at {address} "
                            f"({err})") from None
    try:
        workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
        window = BLOCKS_PER_WORKER * workers * RENDER_BLOCK  # frames past the next to store
        todo: Iterator[int] = iter(cuts)
        futures = as_completed()
        pending: dict[int, bytes] = {}
        nxt = start
        more = next(todo, None)

        def top_up() -> None:  # blocks submitted only within the window after ``nxt``
            nonlocal more
            while more is not None and more < nxt + window:
                futures.add(client.submit(render_block, spec, more,
                                          min(more + RENDER_BLOCK, n), pure=False,
                                          priority=-more))
                more = next(todo, None)

        top_up()
        for fut in futures:
            for k, packed in fut.result():
                pending[k] = packed
            fut.release()
            while nxt in pending:
                yield nxt, pending.pop(nxt)
                nxt += 1
            top_up()
        if nxt < n:
            raise RuntimeError(f"the Dask render ended without frame {nxt}")
    finally:
        client.close()

