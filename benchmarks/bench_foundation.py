"""Foundation benchmarks: forest generation (time, peak memory), scoring at 100 000 trees, and
the stem algorithm on Forest X surface samples.

Run: ``python benchmarks/bench_foundation.py [--repeat 3] [--quick] [--json OUT]``.
Every case runs in a fresh subprocess (peak RSS is that process's ``ru_maxrss``); times are
medians over ``--repeat`` runs. Machines here are shared: compare figures from one run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import textwrap

CASES: dict[str, str] = {
    "import baseline": """
        import tcf_hil.world.forest, tcf_hil.evaluation, tcf_hil.sic
        t = 0.0
    """,
    "generate forest-x (no meshes)": """
        from tcf_hil.world.forest import generate_forest, ground_truth
        from tcf_hil.scenario import load_scenario
        s = load_scenario("forest-x")
        t0 = time.perf_counter(); f = generate_forest(s); ground_truth(f)
        t = time.perf_counter() - t0
    """,
    "generate forest-x + write all files": """
        import tempfile
        from tcf_hil.world.forest import generate_forest
        from tcf_hil.world.forest.output import write_forest
        from tcf_hil.scenario import load_scenario
        s = load_scenario("forest-x")
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter(); write_forest(generate_forest(s), d)
            t = time.perf_counter() - t0
    """,
    "generate 50 ha, 55 000 stems (no meshes)": """
        from tcf_hil.world.forest import generate_forest, ground_truth
        s = _fifty_ha()
        t0 = time.perf_counter(); f = generate_forest(s); ground_truth(f)
        t = time.perf_counter() - t0
    """,
    "generate 50 ha, 55 000 stems + meshes": """
        from tcf_hil.world.forest import generate_forest, stem_mesh, terrain_mesh
        s = _fifty_ha()
        t0 = time.perf_counter(); f = generate_forest(s)
        sm = stem_mesh(f.stems, s.stems.tolerance_mm / 1000)
        tm = terrain_mesh(f.terrain, f.bounds(), s.terrain.tolerance_mm / 1000)
        t = time.perf_counter() - t0
        extra = {"stem_triangles": len(sm.faces), "terrain_triangles": len(tm.faces)}
    """,
    "score 100k vs 100k, greedy (evaluate only)": """
        from tcf_hil.evaluation import EvalConfig, evaluate
        gt, obs = _tables()
        t0 = time.perf_counter(); ev = evaluate(gt, obs, EvalConfig(match="greedy"))
        t = time.perf_counter() - t0
        extra = {"matches": ev.metrics["total_matches"]}
    """,
    "score 100k vs 100k, optimal (evaluate only)": """
        from tcf_hil.evaluation import EvalConfig, evaluate
        gt, obs = _tables()
        t0 = time.perf_counter(); ev = evaluate(gt, obs, EvalConfig(match="optimal"))
        t = time.perf_counter() - t0
        extra = {"matches": ev.metrics["total_matches"]}
    """,
    "score 100k vs 100k, greedy, from JSON files (read+validate+evaluate)": """
        import tempfile, os
        from tcf_hil.evaluation import EvalConfig, evaluate
        from tcf_hil.recording.stems_json import load_stems
        gdoc, odoc = _docs()
        with tempfile.TemporaryDirectory() as d:
            for name, doc in (("g.json", gdoc), ("o.json", odoc)):
                with open(os.path.join(d, name), "w") as fh: json.dump(doc, fh)
            t0 = time.perf_counter()
            ev = evaluate(load_stems(os.path.join(d, "g.json")),
                          load_stems(os.path.join(d, "o.json")), EvalConfig())
            t = time.perf_counter() - t0
    """,
    "stem algorithm, forest-x surface samples, tuned": """
        from tcf_hil.world.forest import generate_forest
        from tcf_hil.world.forest.sampling import sample_surfaces
        from tcf_hil.scenario import load_scenario
        from tcf_hil.sic import identify_stems, stem_params
        c = sample_surfaces(generate_forest(load_scenario("forest-x")))
        t0 = time.perf_counter(); doc = identify_stems(c.xyz, stem_params("tuned"))
        t = time.perf_counter() - t0
        extra = {"points": len(c), "stems_found": doc["total_objects_count"]}
    """,
    "stem algorithm, forest-x surface samples, paper": """
        from tcf_hil.world.forest import generate_forest
        from tcf_hil.world.forest.sampling import sample_surfaces
        from tcf_hil.scenario import load_scenario
        from tcf_hil.sic import identify_stems, stem_params
        c = sample_surfaces(generate_forest(load_scenario("forest-x")))
        t0 = time.perf_counter(); doc = identify_stems(c.xyz, stem_params("paper"))
        t = time.perf_counter() - t0
        extra = {"points": len(c), "stems_found": doc["total_objects_count"]}
    """,
}

PRELUDE = """
import json, resource, time
import numpy as np
extra = {}

def _docs(n=100_000):
    rng = np.random.default_rng(0)
    side = (n / 0.11) ** 0.5   # 1100 stems/ha
    g = rng.uniform(0, side, (n, 2)); o = g + rng.normal(0, 0.3, (n, 2))
    cls = "SCX"
    gd = {"objects": [{"id": i + 1, "cp": [float(g[i, 0]), float(g[i, 1]), 0.0],
                       "class": cls[i % 3], "h": 20.0, "dbh": 0.25} for i in range(n)]}
    od = {"objects": [{"id": i + 1, "cp": [float(o[i, 0]), float(o[i, 1]), 0.0],
                       "class": cls[(i * 5) % 3], "h": 19.5} for i in range(n)]}
    return gd, od

def _fifty_ha():
    from tcf_hil.scenario import scenario_from_dict
    side = (50 * 10000) ** 0.5
    return scenario_from_dict({"name": "fifty-ha", "plot": {"size_m": [side, side]},
        "stems": {"count": 55000}, "terrain": {"kind": "rolling"},
        "distribution": {"kind": "uneven"},
        "track": {"start_m": [0.0, -side / 2, 2.0], "end_m": [0.0, side / 2, 2.0]}})

def _tables():
    from tcf_hil.recording.stems_json import stem_table
    gd, od = _docs()
    return stem_table(gd, "gt"), stem_table(od, "obs")
"""

EPILOGUE = """
print(json.dumps({"seconds": t, "peak_rss_mb":
                  resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, **extra}))
"""


def run_case(body: str) -> dict[str, float]:
    code = PRELUDE + textwrap.dedent(body) + EPILOGUE
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="skip the 50 ha cases")
    ap.add_argument("--json", default=None, help="write the results here")
    a = ap.parse_args()
    results = {}
    print(f"{'case':<72} {'median s':>9} {'min s':>8} {'peak RSS MB':>12}  extra")
    for name, body in CASES.items():
        if a.quick and "50 ha" in name:
            continue
        reps = 1 if "50 ha" in name else a.repeat
        runs = [run_case(body) for _ in range(reps)]
        secs = [r["seconds"] for r in runs]
        extra = {k: v for k, v in runs[-1].items() if k not in ("seconds", "peak_rss_mb")}
        results[name] = {"median_s": statistics.median(secs), "min_s": min(secs),
                         "runs": reps, "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
                         **extra}
        r = results[name]
        print(f"{name:<72} {r['median_s']:>9.3f} {r['min_s']:>8.3f} {r['peak_rss_mb']:>12.0f}  "
              f"{extra if extra else ''}", flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
