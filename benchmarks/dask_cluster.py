"""A two-worker Dask ``LocalCluster`` against the local path on one machine (issue #28).

``python -m benchmarks.dask_cluster [--mp 100] [--repeat 1] [--memory-limit 1GB]
[--pair DIR] [--write]``; ``--table-only --write`` rewrites the section from
``docs/dask_cluster_runs.json`` without running.

The pair is the one of :mod:`benchmarks.scale` (:func:`benchmarks.pipeline.make_big`: tiled
zstd BigTIFFs of a mosaic of real LEVIR/WHU imagery, blurred along a small camera path, 40
pasted changes), generated once (into ``--pair DIR`` when given, kept there for later runs).
Each case runs in a fresh process that reads the files lazily and writes the masks into
zarr arrays on disk, ``keep_reblurred=False``, tile 1024:

* ``local`` -- the default path, ``workers=2`` (a thread pool pulling tiles);
* ``cluster`` -- ``distributed.LocalCluster(n_workers=2, threads_per_worker=1,
  processes=True, memory_limit=...)`` started before the clock, then ``detect_changes`` with
  the client as scheduler (the estimate runs on one worker, the tiles on both).

Measured per case: wall seconds of ``detect_changes``; CPU seconds of it summed over the
client and every process under it (workers and nannies, ``psutil``); the client's peak RSS
and each worker's (``VmHWM`` read in the worker through ``client.run`` at the end, and a
0.2 s psutil sampler of every process as a cross-check); the tasks the scheduler ran and the
largest pickled task the client sent; and a digest of the change and unknown masks, which
must equal the local path's.  Targets (issue #28): the cluster within 1.3x of the local
path's wall time, at most 1 GB per worker.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import importlib
import itertools
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, commit, load_runs, peak_rss_mb, release, run_case, save_runs

RUNS = REPO / "docs" / "dask_cluster_runs.json"
MODES = ("local", "cluster")
#: Issue #28's targets.
MAX_RATIO = 1.3
MAX_WORKER_MB = 1000.0


def _tree_cpu(procs) -> dict[int, float]:
    """CPU seconds (user + system) of each live process in ``procs``, by pid."""
    import psutil

    out = {}
    for p in procs:
        try:
            t = p.cpu_times()
            out[p.pid] = t.user + t.system
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return out


def _digest(a, step: int = 4096) -> str:
    """SHA-256 of a 2-D bool array read in row bands (the same for numpy and zarr)."""
    h = hashlib.sha256()
    for y in range(0, a.shape[0], step):
        h.update(np.ascontiguousarray(np.asarray(a[y : y + step], dtype=bool)).tobytes())
    return h.hexdigest()[:16]


def _vm_hwm_mb() -> float:
    """This process's peak RSS (``VmHWM``), MB: runs in a worker through ``client.run``
    (self-contained: pickled by value)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


def _minflt() -> int:
    """Minor page faults of this process so far (self-contained: runs in workers too)."""
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_minflt)


def _read_mb() -> float:
    """Megabytes this process has read through ``read()`` calls so far, page cache
    included (``rchar`` of ``/proc/self/io``; self-contained: runs in workers too)."""
    with open("/proc/self/io") as f:
        for line in f:
            if line.startswith("rchar:"):
                return int(line.split()[1]) / 2**20
    return float("nan")


class _GraphSpy:
    """Records the tile graph :func:`reblur.dask_backend.decide_tiles` computes: its task
    count and pickled size (what the client ships; the job and the readers enter it once)."""

    def __enter__(self):
        import pickle

        import reblur.dask_backend as db

        self._db, self._real, self.seen = db, db._compute, []

        def spy(graph, *args, **kwargs):
            g = dict(graph.__dask_graph__())
            sizes = {str(k): len(pickle.dumps(v, protocol=5)) for k, v in g.items()}
            self.seen.append(dict(n_tasks=len(g), graph_bytes=len(pickle.dumps(g, protocol=5)),
                                  task_bytes_max=max(sizes.values())))
            return self._real(graph, *args, **kwargs)

        db._compute = spy
        return self

    def __exit__(self, *exc):
        self._db._compute = self._real


class _StageClock:
    """Wall and process-tree CPU at the stage boundaries of ``detect_changes``: the end of
    the motion estimate (``_estimate_stage`` here, ``run_once`` on a cluster) and the start
    of the tile pass (the local path's ``TileJob``, the cluster's ``decide_tiles``)."""

    def __init__(self, procs, cluster: bool):
        self.procs = procs
        self.cluster = cluster
        self.marks: list[tuple[str, float, dict[int, float]]] = []

    def mark(self, name: str) -> None:
        self.marks.append((name, time.perf_counter(), _tree_cpu(self.procs)))

    def __enter__(self):
        import reblur.dask_backend as db
        import reblur.pipeline as pl

        # on a cluster, ``_estimate_stage`` itself is shipped to a worker: left as it is
        self._saved = ([(db, "run_once"), (db, "decide_tiles")] if self.cluster else
                       [(pl, "_estimate_stage"), (pl, "TileJob")])
        self._saved = [(m, n, getattr(m, n)) for m, n in self._saved]
        for m, n, f in self._saved:
            after = n in ("_estimate_stage", "run_once")

            def wrap(*a, _f=f, _after=after, _n=n, **k):
                if not _after:
                    self.mark("tiles")
                out = _f(*a, **k)
                if _after:
                    self.mark("estimated")
                return out

            setattr(m, n, wrap)
        self.mark("start")
        return self

    def __exit__(self, *exc):
        self.mark("end")
        for m, n, f in self._saved:
            setattr(m, n, f)

    def stages(self) -> dict:
        """Wall and CPU seconds (all processes, and the client's alone) of ``estimate``
        (start to the estimate's end), ``fit`` (to the tile pass) and ``tiles`` (to the
        end)."""
        at = {name: (t, c) for name, t, c in self.marks}
        me = self.procs[0].pid
        out = {}
        for stage, a, b in (("estimate", "start", "estimated"), ("fit", "estimated", "tiles"),
                            ("tiles", "tiles", "end")):
            if a in at and b in at:
                ca, cb = at[a][1], at[b][1]
                out[stage] = dict(wall_s=round(at[b][0] - at[a][0], 2),
                                  cpu_s=round(sum(cb.values()) - sum(ca.values()), 2),
                                  client_cpu_s=round(cb.get(me, 0.0) - ca.get(me, 0.0), 2))
        return out


def _stream_summary(records: list[dict]) -> dict:
    """From ``distributed.get_task_stream``: per worker, the seconds its tasks computed and
    the seconds it waited between two tile tasks (the round trip to the scheduler for the
    next one); and the seconds spent on anything but computing (transfers, disk)."""
    out: dict = {"tasks_run": len(records)}
    compute: dict[str, float] = {}
    spans: dict[str, list[tuple[float, float]]] = {}
    other = 0.0
    for r in records:
        w = str(r.get("worker"))
        for ss in r.get("startstops", ()):
            a, b = float(ss["start"]), float(ss["stop"])
            if ss["action"] == "compute":
                compute[w] = compute.get(w, 0.0) + b - a
                if "reblur-tile" in str(r.get("key")):
                    spans.setdefault(w, []).append((a, b))
            else:
                other += b - a
    gaps = []
    for sp in spans.values():
        sp.sort()
        gaps.append(sum(max(0.0, c - b) for (_, b), (c, _) in itertools.pairwise(sp)))
    out.update(compute_s=sorted(compute.values()), other_s=other, gaps_s=sorted(gaps))
    return out


def case(d: Path, mode: str, memory_limit: str = "1GB", tile: int = 1024) -> dict:
    """Run one case on the pair in ``d`` in this process; returns its row."""
    import psutil

    import reblur
    from benchmarks.scale import RssSampler, _open
    from reblur.io import zarr_masks

    ref, obs = _open(d / "ref.tif"), _open(d / "obs.tif")
    H, W = obs.shape[:2]
    work = Path(tempfile.mkdtemp(prefix="reblur-cluster-", dir=d))
    kw: dict = dict(workers=2, tile_size=tile, keep_reblurred=False)
    kw["change_out"], kw["unknown_out"] = zarr_masks(work / "out", (H, W), tile)
    cluster = client = None
    extra: dict = {}
    try:
        if mode == "cluster":
            import distributed

            t = time.perf_counter()
            cluster = distributed.LocalCluster(
                n_workers=2, threads_per_worker=1, processes=True,
                memory_limit=memory_limit, dashboard_address=None)
            client = distributed.Client(cluster)
            client.wait_for_workers(2)
            # a cluster is started once and serves many runs: its workers have imported
            # reblur before the clock, as this process has
            client.run(importlib.import_module, "reblur.pipeline")
            extra["startup_s"] = time.perf_counter() - t
            kw.update(scheduler=client, work_dir=work / "dask")
            extra["worker_pids"] = sorted(client.run(os.getpid).values())
        elif mode != "local":
            raise ValueError(mode)
        me = psutil.Process()
        procs = [me, *me.children(recursive=True)]
        cpu0 = _tree_cpu(procs)
        flt0 = {"client": _minflt(), **(client.run(_minflt) if client is not None else {})}
        rd0 = {"client": _read_mb(), **(client.run(_read_mb) if client is not None else {})}
        stream = None
        clock = _StageClock(procs, cluster=client is not None)
        with RssSampler() as rs, _GraphSpy() as spy, clock:
            if client is not None:
                import distributed

                stream = distributed.get_task_stream(client)
                stream.__enter__()
            t = time.perf_counter()
            res = reblur.detect_changes(ref, obs, **kw)
            dt = time.perf_counter() - t
            cpu1 = _tree_cpu(procs)
            if stream is not None:
                stream.__exit__(None, None, None)
        cpu = {pid: cpu1[pid] - cpu0.get(pid, 0.0) for pid in cpu1}
        flt1 = {"client": _minflt(), **(client.run(_minflt) if client is not None else {})}
        extra["page_faults"] = {k: flt1[k] - flt0.get(k, 0) for k in sorted(flt1)}
        rd1 = {"client": _read_mb(), **(client.run(_read_mb) if client is not None else {})}
        extra["read_mb"] = {k: rd1[k] - rd0.get(k, 0.0) for k in sorted(rd1)}
        wpids = extra.pop("worker_pids", [])
        extra["workers_cpu_s"] = [round(cpu.get(p, 0.0), 2) for p in wpids]
        extra["others_cpu_s"] = round(sum(v for p, v in cpu.items()
                                          if p != me.pid and p not in wpids), 2)
        row = dict(mode=mode, mp=H * W / 1e6, time_s=dt, cpu_s=sum(cpu.values()),
                   client_cpu_s=cpu.get(me.pid, 0.0), timings=res.timings,
                   seconds=res.decision.get("seconds"), client_mb=peak_rss_mb(),
                   change=_digest(res.change), unknown=_digest(res.unknown),
                   regions=len(res.regions), incomplete=res.decision.get("incomplete_tiles"),
                   stages=clock.stages(), sampled=rs.summary(), load=os.getloadavg()[0], **extra)
        if client is not None:
            hwm = client.run(_vm_hwm_mb)
            row.update(memory_limit=memory_limit, worker_mb=sorted(hwm.values()),
                       **(spy.seen[0] if spy.seen else {}), **_stream_summary(stream.data))
        return row
    finally:
        release(client, cluster, work)


def _per_process(rs: list[dict], key: str, scale: float) -> str:
    """``client / worker / worker`` medians of the per-process counts ``r[key]`` (workers
    by count, largest last), times ``scale``; "-" where a run lacks them."""
    if not all(key in r for r in rs):
        return "-"
    per = [[r[key]["client"]] + sorted(v for k, v in r[key].items() if k != "client")
           for r in rs]
    if len({len(p) for p in per}) != 1:
        return "-"
    return " / ".join(f"{float(np.median(col)) * scale:.0f}" for col in zip(*per, strict=True))


def main(mp: float = 100, repeat: int = 1, memory_limit: str = "1GB",
         pair: Path | None = None) -> list[dict]:
    """Generate (or reuse) the pair, run every mode ``repeat`` times in fresh processes
    (interleaved), record the rows in :data:`RUNS` and return them."""
    from benchmarks.pipeline import make_big
    from benchmarks.scale import _side

    side = _side(mp)
    tmp = None
    if pair is None:
        tmp = tempfile.TemporaryDirectory(dir="/tmp", prefix="reblur-cluster-")
        pair = Path(tmp.name)
    pair.mkdir(parents=True, exist_ok=True)
    gen = None
    if not ((pair / "ref.tif").exists() and (pair / "obs.tif").exists()):
        t = time.perf_counter()
        make_big(pair, side)
        gen = time.perf_counter() - t
        print(f"[dask_cluster] {mp:g} MP pair generated in {gen:.0f} s", flush=True)
    runs = load_runs(RUNS)
    new: list[dict] = []
    commit_, day = commit(), datetime.date.today().isoformat()
    try:
        for i in range(repeat):
            for mode in MODES:
                load0 = os.getloadavg()[0]
                r = run_case("benchmarks.dask_cluster", "--case", str(pair), "--mode", mode,
                             "--memory-limit", memory_limit, timeout=3600, blas_threads=None)
                r.update(run=i, commit=commit_, date=day, load_before=load0)
                new.append(r)
                runs.append(r)
                save_runs(RUNS, runs)
                print(f"[dask_cluster] {json.dumps(r)}", flush=True)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return new


def _cell(rs: list[dict], key: str, fmt: str = "{:.1f}") -> str:
    v = [r[key] for r in rs]
    if len(v) == 1:
        return fmt.format(v[0])
    return f"{fmt.format(float(np.median(v)))} ({fmt.format(min(v))}-{fmt.format(max(v))})"


def _waits(rs: list[dict]) -> str:
    """A sentence on the workers' waits between tile tasks (task stream), if recorded."""
    gaps = [g for r in rs for g in r.get("gaps_s", [])]
    if not gaps:
        return ""
    return (f"  Each worker waited {min(gaps):.1f}-{max(gaps):.1f} s in all between its tile "
            "tasks (the round trip to the scheduler for the next one).")


def _earlier(rows: list[dict], n: int = 3) -> list[str]:
    """One line per earlier commit (the ``n`` newest): median wall and tile-pass CPU."""
    order = list(dict.fromkeys(r["commit"] for r in reversed(rows)))[:n]
    out = []
    for c in order:
        cells = []
        for mode in MODES:
            rs = [r for r in rows if r["commit"] == c and r["mode"] == mode]
            if not rs:
                continue
            cell = f"{mode} {float(np.median([r['time_s'] for r in rs])):.1f} s"
            tiles = [r["stages"]["tiles"]["cpu_s"] for r in rs if "tiles" in r.get("stages", {})]
            if tiles:
                cell += f" (tile pass {float(np.median(tiles)):.1f} s CPU)"
            cells.append(cell)
        if cells:
            out.append(f"Earlier, {c} ({rs[0]['date']}, load up to "
                       f"{max(r['load'] for r in rows if r['commit'] == c):.1f}): "
                       + ", ".join(cells) + ".")
    return [""] + out if out else []


def markdown(rows: list[dict]) -> str:
    """The section: the newest commit's rows, median (range) over its runs."""
    if not rows:
        return "## Dask LocalCluster against the local path\n\nNo runs recorded."
    last = rows[-1]["commit"]
    earlier = _earlier([r for r in rows if r["commit"] != last])
    rows = [r for r in rows if r["commit"] == last]
    by = {m: [r for r in rows if r["mode"] == m] for m in MODES}
    lines = [
        "## Dask LocalCluster against the local path (`python -m benchmarks.dask_cluster`)",
        "",
        "The 100 MP pair of `benchmarks.scale` (tiled zstd BigTIFFs read lazily, masks to zarr "
        "on disk, `keep_reblurred=False`, tile 1024); each case in a fresh process.  "
        "`cluster`: a `distributed.LocalCluster` of 2 single-thread worker processes "
        "(`memory_limit` per worker as given), started before the clock.  CPU: the client "
        "and every process under it.  Worker RSS: each worker's `VmHWM`.  Median (range) "
        "over the runs.  Page faults: minor faults during the run, client / each worker; read: "
        "the bytes they read from files (`rchar`, page cache included), workers by count.  "
        "Graph: the tile pass's tasks and their pickled size (the shared job, the largest "
        "entry, enters it once).",
        "",
        "| mode | runs | wall (s) | CPU (s) | estimate: wall / CPU (s) | decision's fit: "
        "wall / CPU (s) | tile pass: wall / CPU (s), client's CPU | client peak RSS (MB) | "
        "workers' peak RSS (MB) | page faults (k) | read (MB) | graph: tasks, bytes | masks | "
        "load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ref = by["local"][0] if by["local"] else None

    def stage(rs: list[dict], name: str, client: bool = False) -> str:
        rs = [r for r in rs if name in r.get("stages", {})]
        if not rs:
            return "-"
        med = {k: float(np.median([r["stages"][name].get(k, np.nan) for r in rs]))
               for k in ("wall_s", "cpu_s", "client_cpu_s")}
        out = f"{med['wall_s']:.1f} / {med['cpu_s']:.1f}"
        return out + (f", {med['client_cpu_s']:.1f}" if client else "")

    for mode in MODES:
        rs = by[mode]
        if not rs:
            continue
        workers = ("-" if mode == "local" else
                   ", ".join(f"{max(r['worker_mb'][i] for r in rs):.0f}"
                             for i in range(len(rs[0]["worker_mb"]))))
        faults = _per_process(rs, "page_faults", 1e-3)
        read = _per_process(rs, "read_mb", 1.0)
        graph = ("-" if mode == "local" else
                 f"{rs[0]['n_tasks']}, {rs[0]['graph_bytes'] / 1e3:.0f} k (largest entry "
                 f"{rs[0]['task_bytes_max'] / 1e3:.0f} k)")
        same = ("-" if ref is None or mode == "local" else
                "same" if all((r["change"], r["unknown"]) == (ref["change"], ref["unknown"])
                              for r in rs) else "DIFFER")
        loads = [r["load"] for r in rs]
        lines.append(
            f"| {mode} | {len(rs)} | {_cell(rs, 'time_s')} | {_cell(rs, 'cpu_s')} | "
            f"{stage(rs, 'estimate')} | {stage(rs, 'fit')} | {stage(rs, 'tiles', True)} | "
            f"{_cell(rs, 'client_mb', '{:.0f}')} | {workers} | {faults} | {read} | {graph} | "
            f"{same} | {min(loads):.1f}-{max(loads):.1f} |")
    if by["local"] and by["cluster"]:
        ratio = (float(np.median([r["time_s"] for r in by["cluster"]]))
                 / float(np.median([r["time_s"] for r in by["local"]])))
        cpu = (float(np.median([r["cpu_s"] for r in by["cluster"]]))
               / float(np.median([r["cpu_s"] for r in by["local"]])))
        worst = max(max(r["worker_mb"]) for r in by["cluster"])
        ok = ratio <= MAX_RATIO and worst <= MAX_WORKER_MB
        lines += [
            "",
            f"Cluster / local: wall {ratio:.2f}x, CPU {cpu:.2f}x; largest worker "
            f"{worst:.0f} MB (memory_limit {by['cluster'][0]['memory_limit']}).  Targets "
            f"(issue #28): wall <= {MAX_RATIO}x, <= {MAX_WORKER_MB:.0f} MB per worker: "
            f"{'met' if ok else 'NOT met'}.  Cluster start-up, with the workers' import of "
            f"reblur (not timed above): {_cell(by['cluster'], 'startup_s')} s."
            + _waits(by["cluster"]),
        ]
    lines += ["", f"Commit {last}, {rows[-1]['date']}; load: the 1-minute load average at "
              "the end of each case (2 cores; above 2, something else shared them).", *earlier]
    return "\n".join(lines)


def _cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=Path, help="(internal) directory holding ref.tif, obs.tif")
    ap.add_argument("--mode", default="local", choices=MODES)
    ap.add_argument("--mp", type=float, default=100.0, help="pair size in megapixels")
    ap.add_argument("--repeat", type=int, default=1, help="runs per mode (interleaved)")
    ap.add_argument("--memory-limit", default="1GB", help="memory_limit of each worker")
    ap.add_argument("--pair", type=Path, help="directory of the pair (generated if missing, "
                    "kept)")
    ap.add_argument("--write", action="store_true", help="write the docs/benchmarks.md section")
    ap.add_argument("--table-only", action="store_true",
                    help="render the section from docs/dask_cluster_runs.json without running")
    a = ap.parse_args()
    if a.case is not None:
        print(json.dumps(case(a.case, a.mode, a.memory_limit)))
        return
    if not a.table_only:
        main(a.mp, a.repeat, a.memory_limit, a.pair)
    md = markdown(load_runs(RUNS))
    print(md)
    if a.write:
        from benchmarks.run import write_section

        write_section("dask_cluster", md)


if __name__ == "__main__":
    _cli()
