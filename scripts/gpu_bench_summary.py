#!/usr/bin/env python3
"""The Markdown tables of a `scripts/gpu-bench.sh` run, from the JSON files it left in its folder.

Usage: python3 scripts/gpu_bench_summary.py OUT_DIR   (prints to stdout)

Standard library only, so that it runs wherever the benchmark ran. Missing files (a step the
budget skipped) leave their table out; `skipped.txt` says which.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

STAGES = (
    "lock",
    "take",
    "render_queue",
    "render_encode",
    "render_submit",
    "render_device",
    "render_extract",
    "answer",
)


def load(folder: Path, name: str) -> dict[str, Any] | None:
    path = folder / name
    if not path.exists():
        return None
    return json.loads(path.read_text(encoding="utf-8"))


def rate(result: dict[str, Any]) -> str:
    value = result.get("steps_per_second")
    return "–" if value is None else f"{value:,.0f}"


def ms(result: dict[str, Any], key: str) -> str:
    value = result.get(key)
    return "–" if value is None else f"{value:.2f}"


def cores(folder: Path, name: str) -> str:
    """The machine's busy cores while step `name` ran (its cpu-NAME.txt), or a dash."""
    path = folder / f"cpu-{name}.txt"
    if not path.exists():
        return "–"
    return path.read_text(encoding="utf-8").strip() or "–"


def busiest(result: dict[str, Any]) -> str:
    breakdown = result.get("breakdown") or {}
    stages = breakdown.get("stages") or {}
    if not stages:
        return "–"
    name = max(stages, key=lambda s: stages[s]["busy"] or 0.0)
    return f"{name} {stages[name]['busy']:.2f}"


def figures(entry: dict[str, Any] | None) -> str:
    """A stage's cell: microseconds per step and busy share, or a dash (a stage not counted)."""
    if entry is None or entry.get("us_per_step") is None:
        return "–"
    return f"{entry['us_per_step']:.1f} ({entry['busy']:.2f})"


def drawing(result: dict[str, Any]) -> str:
    """How busy the device kept drawing (its own clock), where the server timed it, or a dash."""
    entry = (result.get("breakdown") or {}).get("gpu_drawing")
    if not entry or entry.get("busy") is None:
        return "–"
    return f"{entry['busy']:.2f}"


def standard(folder: Path) -> list[str]:
    report = load(folder, "standard.json")
    if report is None:
        return []
    # Reports of a server older than the compute rasteriser do not say which one drew.
    rasterizer = f", {report['rasterizer']} rasterizer" if report.get("rasterizer") else ""
    lines = [
        "## Scenarios (render threads: auto)",
        "",
        f"Renderer: {report['renderer']} ({report['backend']}{rasterizer}); client machine: {report['cpus']} CPUs, "
        f"{report['cpu']}.",
        "",
        "| scenario | episodes | steps/s | p50 ms | p99 ms |",
        "|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['scenario']} | {r['episodes']} | {rate(r)} | {ms(r, 'p50_ms')} | {ms(r, 'p99_ms')} |"
        for r in report["results"]
    ]
    lines += [
        "",
        "Where the server's time went (µs per step, and how busy each stage kept its threads;",
        "gpu_drawing: the part of render_device the device spent drawing, by its own clock,",
        "where the server times it):",
        "",
        "| scenario | " + " | ".join(STAGES) + " | gpu_drawing |",
        "|---|" + "---:|" * (len(STAGES) + 1),
    ]
    for r in report["results"]:
        breakdown = r.get("breakdown") or {}
        stages = breakdown.get("stages") or {}
        cells = [figures(stages.get(stage)) for stage in STAGES] + [figures(breakdown.get("gpu_drawing"))]
        lines.append(f"| {r['scenario']} | " + " | ".join(cells) + " |")
    cpu_rows = [
        f"| {r['scenario']} | {client_cpu(r)} | {figures(((r.get('breakdown') or {}).get('cpu') or {}).get('process'))} "
        f"| {server_threads(r)} |"
        for r in report["results"]
        if r.get("client_cpu_seconds") is not None or (r.get("breakdown") or {}).get("cpu")
    ]
    if cpu_rows:
        lines += [
            "",
            "CPU per step (core-µs per step, and cores kept busy; the server's by its threads, the",
            "three busiest):",
            "",
            "| scenario | client | server | server's threads |",
            "|---|---:|---:|---|",
            *cpu_rows,
        ]
    return [*lines, ""]


def client_cpu(result: dict[str, Any]) -> str:
    """The client's CPU over the measured seconds: core-µs per step (cores busy), or a dash."""
    seconds, per_step = result.get("client_cpu_seconds"), result.get("client_cpu_us_per_step")
    if seconds is None or per_step is None or not result.get("seconds"):
        return "–"
    return f"{per_step:.1f} ({seconds / result['seconds']:.2f})"


def server_threads(result: dict[str, Any]) -> str:
    """The server's three busiest groups of threads, by CPU, or a dash."""
    threads = (((result.get("breakdown") or {}).get("cpu") or {}).get("threads")) or {}
    busiest = sorted(threads.items(), key=lambda item: -(item[1].get("us_per_step") or 0.0))[:3]
    return ", ".join(f"{name} {figures(entry)}" for name, entry in busiest) or "–"


def series(folder: Path, title: str, header: str, files: list[tuple[str, str]]) -> list[str]:
    """A table of the scenarios of each file.

    Client processes × episodes each (the JSON holds the episodes of all processes), and the
    step's busy cores, machine-wide, on its first row.
    """
    rows = []
    for label, name in files:
        report = load(folder, name)
        if report is None:
            continue
        for i, r in enumerate(report["results"]):
            busy = cores(folder, name.removesuffix(".json")) if i == 0 else ""
            processes = max(int(r.get("processes", 1)), 1)
            rows.append(
                f"| {label} | {r['scenario']} | {processes} × {r['episodes'] // processes} | {rate(r)} "
                f"| {ms(r, 'p50_ms')} | {busiest(r)} | {drawing(r)} | {busy} |"
            )
    if not rows:
        return []
    return [
        f"## {title}",
        "",
        f"| {header} | scenario | processes × episodes | steps/s | p50 ms | busiest stage (busy) "
        "| device drawing (busy) | cores busy |",
        "|---|---|---:|---:|---:|---|---:|---:|",
        *rows,
        "",
    ]


def client_cores(result: dict[str, Any]) -> str:
    """The cores the client processes kept busy over the measured seconds, or a dash."""
    seconds = result.get("client_cpu_seconds")
    return "–" if seconds is None or not result.get("seconds") else f"{seconds / result['seconds']:.1f}"


def scale_out(folder: Path) -> list[str]:
    rows = []
    for n in (2, 4, 8):
        apart, one = load(folder, f"servers-{n}.json"), load(folder, f"one-{n}.json")
        if apart is None or one is None:
            continue
        busy = f"{cores(folder, f'servers-{n}')} / {cores(folder, f'one-{n}')}"
        for mine, theirs in zip(apart["results"], one["results"], strict=False):
            a, b = mine["steps_per_second"] or 0.0, theirs["steps_per_second"] or 0.0
            faster = "servers" if a > b else "one server"
            ratio = max(a, b) / max(min(a, b), 1.0)
            rows.append(
                f"| {n} | {n} | {mine['scenario']} | {a:,.0f} | {b:,.0f} | {faster} ({ratio:.2f}×) | {busy} "
                f"| {client_cores(mine)} |"
            )
    doubled = load(folder, "servers-8x2.json")
    for r in doubled["results"] if doubled else []:
        rows.append(
            f"| 8 | 16 | {r['scenario']} | {rate(r)} | – | – | {cores(folder, 'servers-8x2')} / – | {client_cores(r)} |"
        )
    shared = load(folder, "servers-8-shared.json")
    workers_file = folder / "servers-8-shared-workers.txt"
    workers = workers_file.read_text(encoding="utf-8").strip() if workers_file.exists() else "?"
    for r in shared["results"] if shared else []:
        rows.append(
            f"| 8 (--worker-threads {workers}) | 8 | {r['scenario']} | {rate(r)} | – | – "
            f"| {cores(folder, 'servers-8-shared')} / – | {client_cores(r)} |"
        )
    for name, processes in (("servers-8-unix", 8), ("servers-8x2-unix", 16)):
        unix = load(folder, f"{name}.json")
        for r in unix["results"] if unix else []:
            rows.append(
                f"| 8 (Unix sockets) | {processes} | {r['scenario']} | {rate(r)} | – | – | {cores(folder, name)} / – "
                f"| {client_cores(r)} |"
            )
    if not rows:
        return []
    return [
        "## Scale-out: N servers against one, the same client processes (64 episodes each)",
        "",
        "| N servers | client processes | scenario | N servers, steps/s | one server, steps/s | faster "
        "| cores busy (N servers / one) | of them the clients' |",
        "|---:|---:|---|---:|---:|---|---:|---:|",
        *rows,
        "",
    ]


def views_table(report: dict[str, Any], title: str) -> list[str]:
    """One run of the views bench: each case's views/s, a column per culling setting, and where
    the renderer timed its device, the device's drawing per view (µs, by its clock) in brackets."""
    columns = list(next(iter(report["cases"].values()), {}))
    drawing = report.get("gpu_us_per_view") or {}
    unit = "views/s (the device's drawing, µs a view)" if drawing else "views/s"
    lines = [
        f"## {title}",
        "",
        f"Adapter: {report['adapter']}; rasterizer {report.get('rasterizer', 'pipeline')}; "
        f"{report['seconds']} s a case; {unit}.",
        "",
        "| case | " + " | ".join(columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]

    def cell(case: str, column: str) -> str:
        views = f"{report['cases'][case][column]:,.0f}"
        us = (drawing.get(case) or {}).get(column)
        return views if us is None else f"{views} ({us:.1f})"

    for case in report["cases"]:
        lines.append(f"| {case} | " + " | ".join(cell(case, c) for c in columns) + " |")
    return [*lines, ""]


def renderer(folder: Path) -> list[str]:
    """The renderer alone: each case of the views bench in one process (the graphics pipeline,
    then the compute rasteriser), then the views per second of several processes rendering at
    once, summed (a process whose file is missing failed: the row says how many answered)."""
    alone = load(folder, "renderer.json")
    lines: list[str] = []
    if alone is not None:
        lines += views_table(alone, "The renderer alone, no server (esrp-render's views bench)")
    compute = load(folder, "renderer-compute.json")
    if compute is not None:
        lines += views_table(compute, "The compute rasteriser alone, no server (the views bench)")
    together = {n: [load(folder, f"renderer-x{n}-{i}.json") for i in range(n)] for n in (4, 8)}
    answered = {n: [r for r in reports if r is not None] for n, reports in together.items()}
    first = next((reports[0] for reports in answered.values() if reports), None)
    if first is None:
        return lines
    cases = list(first["cases"])
    rows = []
    if alone is not None:
        cells = " | ".join(f"{alone['cases'].get(c, {}).get('culling on', 0.0):,.0f}" for c in cases)
        rows.append(f"| 1 | 1 | {cells} | {cores(folder, 'renderer')} |")
    for n, reports in answered.items():
        if reports:
            total = [sum(r["cases"].get(c, {}).get("culling on", 0.0) for r in reports) for c in cases]
            cells = " | ".join(f"{t:,.0f}" for t in total)
            rows.append(f"| {n} | {len(reports)} | {cells} | {cores(folder, f'renderer-x{n}')} |")
    lines += [
        "Several processes rendering at once, each with a device of its own (culling on; views/s "
        "summed over the processes that answered):",
        "",
        "| processes | answered | " + " | ".join(cases) + " | cores busy |",
        "|---:|---:|" + "---:|" * len(cases) + "---:|",
        *rows,
        "",
    ]
    return lines


def python(folder: Path) -> list[str]:
    rows = []
    for step, transport in (
        ("python", "TCP"),
        ("python-unix", "Unix socket"),
        ("python-spread-4", "4 servers' sockets"),
        ("python-spread-8", "8 servers' sockets"),
    ):
        report = load(folder, f"{step}.json")
        if report is None:
            continue
        results = report.get("results", report)
        busy = cores(folder, step)
        for r in results if isinstance(results, list) else []:
            name = r.get("name") or r.get("scenario")
            steps = r.get("steps_per_second")
            cpu = r.get("client_cpu_us_per_step")
            rows.append(
                f"| {name} | {transport} | {'–' if steps is None else f'{steps:,.0f}'} "
                f"| {'–' if cpu is None else f'{cpu:.0f}'} | {busy} |"
            )
    if not rows:
        return []
    return [
        "## python -m esrp.bench",
        "",
        "| scenario | to the server | steps/s | client CPU per step, µs | cores busy |",
        "|---|---|---:|---:|---:|",
        *rows,
        "",
    ]


def main(argv: list[str]) -> int:
    if len(argv) != 2 or not Path(argv[1]).is_dir():
        print("usage: gpu_bench_summary.py OUT_DIR", file=sys.stderr)
        return 2
    folder = Path(argv[1])
    lines = ["# gpu-bench", ""]
    machine = folder / "machine.txt"
    if machine.exists():
        lines += ["```text", machine.read_text(encoding="utf-8").strip(), "```", ""]
    lines += standard(folder)
    lines += series(
        folder,
        "The compute rasteriser (--render-rasterizer compute)",
        "servers",
        [
            ("1", "compute.json"),
            ("8", "compute-servers-8.json"),
            ("8", "compute-servers-8x2.json"),
        ],
    )
    lines += series(folder, "The OpenGL backend (--render-backend gl)", "backend", [("gl", "gl.json")])
    lines += scale_out(folder)
    lines += series(
        folder,
        "Batches in flight per render thread (--render-pipeline; one server)",
        "batches in flight",
        [(str(d), f"pipeline-{d}.json") for d in (1, 2, 3)],
    )
    lines += series(
        folder,
        "The device's timestamps (--render-timestamps; one server, one batch in flight): what they cost",
        "timestamps",
        [("auto (on a GPU)", "pipeline-1.json"), ("off", "timestamps-off.json")],
    )
    lines += series(
        folder,
        "Depth buffers (--render-depth-buffers; one server, one batch in flight)",
        "depth buffers",
        [("shared", "pipeline-1.json"), ("per-page", "depth-per-page.json")],
    )
    for depth in ("shared", "per-page"):
        report = load(folder, f"renderer-depth-{depth}.json")
        if report is not None:
            lines += views_table(report, f"The renderer alone with --render-depth-buffers {depth}")
    lines += renderer(folder)
    lines += series(
        folder,
        "Render threads (one server)",
        "render threads",
        [(str(t), f"threads-{t}.json") for t in (1, 2, 4, 8)],
    )
    lines += series(
        folder,
        "Render devices (one server, threads auto)",
        "render devices",
        [(str(d), f"devices-{d}.json") for d in (2, 4)],
    )
    lines += series(
        folder,
        "Episodes (batch-64 scenario, one StepBatch of all episodes)",
        "episodes",
        [(str(e), f"episodes-{e}.json") for e in (1, 4, 16, 64, 256, 1024)],
    )
    lines += series(
        folder,
        "Client processes (stream-mux-64, 64 episodes each)",
        "processes",
        [(str(p), f"clients-{p}.json") for p in (1, 2, 4, 8)],
    )
    lines += python(folder)
    skipped = folder / "skipped.txt"
    left_out = (
        [line for line in skipped.read_text(encoding="utf-8").splitlines() if line]
        if skipped.exists()
        else []
    )
    lines += ["## Skipped", "", *([f"- {s}" for s in left_out] or ["- nothing"]), ""]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
