"""One command for all figures (issue #21): runs every benchmark, then writes docs/results.md.

Every `bench/bench_*.py` runs as its own child process (`--quick` when given here; the
studies `study_*.py` and `soak.py` only with `--studies`: they take hours), each writing
`bench/results/<name>.json` through `bench/results_io.py`. The page is then rendered from
every JSON present: a header (machines, loads, dates, the version of every baseline), a
summary of what ran, and one section per bench: its fixed introduction
(`bench/results_sections.py`), the tables of `figures["tables"]` and `figures["notes"]`.
A bench that failed or wrote nothing is listed with the reason; a study without JSON keeps
the text of its last measurement, dated. `bench/results/device_suite.json` (from
`bench/device_suite.sh` on a GPU machine) adds a cuda section.

    python bench/run_all.py [--quick] [--studies] [--only bench_localize] [--render-only]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from results_sections import INTRO, LEGACY, SECTIONS

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
RESULTS = BENCH / "results"
STATUS = RESULTS / "run_all_status.json"
DOC = ROOT / "docs" / "results.md"
DEVICE_SUITE = "device_suite"


def is_study(name: str) -> bool:
    return name.startswith("study_") or name == "soak"


def scripts(studies: bool) -> list[str]:
    names = sorted(p.stem for p in BENCH.glob("bench_*.py"))
    if studies:
        names += [*sorted(p.stem for p in BENCH.glob("study_*.py")), "soak"]
    return names


def run_one(name: str, quick: bool, backend: str | None, timeout_s: float) -> dict:
    """Run one script; its status: ok, failed or no JSON, with the reason and seconds."""
    logs = RESULTS / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(BENCH / f"{name}.py"), *(["--quick"] if quick else []),
           *(["--backend", backend] if backend else [])]
    started = time.time()
    print(f"[run_all] {' '.join(cmd[1:])}", flush=True)
    log = logs / f"{name}.log"
    try:
        with open(log, "w") as out:
            rc = subprocess.run(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT,
                                timeout=timeout_s).returncode
    except subprocess.TimeoutExpired:
        rc = None
    seconds = round(time.time() - started, 1)
    status = {"status": "ok", "reason": "", "seconds": seconds, "date": _utc(started),
              "command": " ".join(["python", *map(_relative, cmd[1:])])}
    path = RESULTS / f"{name}.json"
    if rc is None:
        status.update(status="failed", reason=f"stopped after {timeout_s:.0f} s (timeout)")
    elif rc != 0:
        status.update(status="failed", reason=f"exit {rc}: {_last_line(log)}")
    elif not path.exists() or path.stat().st_mtime < started:
        status.update(status="no JSON", reason=f"finished without writing {_relative(path)}")
    elif _figures(path) is None:
        status.update(status="no JSON", reason=f"{_relative(path)} is not in the results_io "
                                               "shape (no figures)")
    print(f"[run_all] {name}: {status['status']} in {seconds:.0f} s {status['reason']}",
          flush=True)
    return status


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t))


def _relative(path) -> str:
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def _last_line(log: Path) -> str:
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines()
             if line.strip()]
    return (lines[-1] if lines else "no output")[:300]


def _figures(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data.get("figures") if isinstance(data, dict) and isinstance(
        data.get("figures"), dict) else None


# ------------------------------------------------------------------------ rendering
def load_results() -> dict[str, dict]:
    """Every JSON under bench/results in the results_io shape, by file name."""
    found = {}
    for path in sorted(RESULTS.glob("*.json")):
        try:
            data = json.loads(path.read_text())
        except ValueError:
            continue
        if isinstance(data, dict) and isinstance(data.get("figures"), dict):
            found[path.stem] = data  # bench_x.json; other files (bench_x_before.json) of a
            # bench's own making are not its result
    return found


def cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        value = f"{value:g}"
    return str(value).replace("|", "\\|").replace("\n", " ")


def markdown_table(rows: list[dict]) -> str:
    if not rows:
        return "(no rows)"
    columns = list(dict.fromkeys(key for row in rows for key in row))
    lines = ["| " + " | ".join(cell(c) for c in columns) + " |",
             "| " + " | ".join("---" for _ in columns) + " |"]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def render_figures(figures: dict, level: str = "") -> list[str]:
    out = []
    for caption, rows in (figures.get("tables") or {}).items():
        out += [f"{level}{caption}:" if level else f"**{caption}**", "",
                markdown_table(rows if isinstance(rows, list) else [rows]), ""]
    notes = figures.get("notes") or []
    out += [f"- {note}" for note in notes] + ([""] if notes else [])
    return out


def header(results: dict[str, dict]) -> list[str]:
    machines = sorted({_machine(d) for n, d in results.items()
                       if not n.startswith(DEVICE_SUITE)})
    dates = sorted(d.get("date", "") for d in results.values() if d.get("date"))
    versions: dict[str, set] = {}
    for data in results.values():
        for package, ver in (data.get("versions") or {}).items():
            versions.setdefault(package, set()).add(ver or "not installed")
    out = ["# Measured results", "", INTRO, ""]
    out += [f"- Machine{'s' if len(machines) > 1 else ''}: " + "; ".join(machines)]
    if dates:
        out.append(f"- Measured: {dates[0]} to {dates[-1]}")
    out.append("- Versions (mcl3d, its core packages and every baseline the benches ran): "
               + ", ".join(f"{p} {' / '.join(sorted(v))}" for p, v in sorted(versions.items())))
    out.append(f"- Page generated {_utc(time.time())} by `python bench/run_all.py`.")
    return [*out, ""]


def _machine(data: dict) -> str:
    m = data.get("machine") or {}
    return (f"{m.get('cpu', '?')}, {m.get('cores', '?')} logical cores, "
            f"{m.get('memory_gib', '?')} GiB, Python {m.get('python', '?')}")


def summary_table(results: dict[str, dict], statuses: dict[str, dict], names: list[str]
                  ) -> list[str]:
    rows = []
    for name in names:
        data, status = results.get(name), statuses.get(name, {})
        if data:
            state = status.get("status", "ok")
            if state != "ok":
                state = f"{state} ({status.get('reason', '')}); JSON from an earlier run"
        elif is_study(name):
            state = status.get("status") or "not run (a study: `run_all.py --studies`)"
        else:
            state = f"{status.get('status', 'not run')}: {status.get('reason', '')}".rstrip(": ")
        load = (data or {}).get("load_average") or {}
        rows.append({"bench": f"`{name}`", "status": state, "date": (data or {}).get("date"),
                     "load before / after": f"{load['before']} / {load['after']}" if load else "",
                     "wall s": (data or {}).get("wall_s"),
                     "command": f"`{data['command']}`" if data and data.get("command") else ""})
    return ["## What ran", "", markdown_table(rows), ""]


def section(name: str, title: str, intro: str, results: dict, statuses: dict) -> list[str]:
    out = [f"## {title}", ""]
    data, status = results.get(name), statuses.get(name, {})
    if data is None and name in LEGACY:
        measured, text = LEGACY[name]
        old = sorted(p.name for p in RESULTS.glob(f"{name}*.json"))
        out += [f"*Measured on {measured} by an earlier run of `bench/{name}.py`; not "
                f"regenerated here (no `bench/results/{name}.json` in the results_io shape"
                + (f"; older files: {', '.join(old)}" if old else "") + ").*", "",
                text.strip(), ""]
        return out
    if intro:
        out += [intro, ""]
    if data is None:
        if not status:
            return [*out, f"*No results: `bench/{name}.py` has not run (no "
                          f"`bench/results/{name}.json`).*", ""]
        return [*out, f"*No results: `bench/{name}.py` {status['status']}: "
                      f"{status.get('reason', '')}.*", ""]
    out += [f"`{data.get('command', name)}`, {data.get('date', '')}, load "
            f"{(data.get('load_average') or {}).get('before')} at the start, "
            f"{data.get('wall_s')} s.", ""]
    if status.get("status") not in (None, "ok"):
        out += [f"*This run: {status['status']} ({status.get('reason', '')}); the figures "
                "below are from the earlier run dated above.*", ""]
    return out + render_figures(data["figures"])


def device_section(results: dict) -> list[str]:
    data = results.get(DEVICE_SUITE)
    out = ["## cuda (device suite)", ""]
    if data is None:
        return [*out, "*No GPU measured: `bench/results/device_suite.json` is absent. Run "
                "`bash bench/device_suite.sh` on a machine with cuda.*", ""]
    figures = data["figures"]
    out += [f"`bash bench/device_suite.sh` on {figures.get('device', '?')} "
            f"({data.get('date', '')}, {data.get('wall_s')} s, host: {_machine(data)}); the "
            "papers' targets first, then each bench's tables on cuda.", ""]
    out += render_figures(figures)
    titles = {name: title for name, title, _ in SECTIONS}
    for name, bench in (figures.get("benches") or {}).items():
        if isinstance(bench, dict) and isinstance(bench.get("figures"), dict):
            out += [f"### cuda: {titles.get(name, name)}", ""]
            out += render_figures({"tables": bench["figures"].get("tables") or {}})
    return out


def render(statuses: dict[str, dict]) -> str:
    results = load_results()
    listed = [name for name, _, _ in SECTIONS]
    extra = sorted(n for n in set(results) | set(statuses)
                   if n not in listed and not n.startswith(DEVICE_SUITE))
    known = {p.stem for p in BENCH.glob("*.py")}
    names = [n for n in listed if n in known or n in results] + [n for n in extra
                                                                  if n in known]
    out = header(results) + summary_table(results, statuses, names)
    for name, title, intro in [*[s for s in SECTIONS if s[0] in names],
                               *[(n, n, "") for n in extra if n in names]]:
        out += section(name, title, intro, results, statuses)
    out += device_section(results)
    return "\n".join(out).rstrip() + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="every bench with --quick")
    ap.add_argument("--studies", action="store_true", help="also the studies and soak (hours)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only these (e.g. bench_gicp)")
    ap.add_argument("--backend", help="passed to every bench (default: each bench's own)")
    ap.add_argument("--timeout", type=float, help="seconds per bench (default 900 quick, 7200)")
    ap.add_argument("--render-only", action="store_true", help="only render docs/results.md")
    args = ap.parse_args()
    statuses = json.loads(STATUS.read_text()) if STATUS.exists() else {}
    if not args.render_only:
        names = ([Path(n).stem for n in args.only] if args.only else scripts(args.studies))
        missing = [n for n in names if not (BENCH / f"{n}.py").exists()]
        if missing:
            sys.exit(f"run_all: no bench/{missing[0]}.py; the benches: "
                     + ", ".join(scripts(True)))
        timeout = args.timeout or (900 if args.quick else 7200)
        t0 = time.time()
        for name in names:
            statuses[name] = run_one(name, args.quick, args.backend, timeout)
            STATUS.parent.mkdir(parents=True, exist_ok=True)
            STATUS.write_text(json.dumps(statuses, indent=2))
        print(f"[run_all] {len(names)} scripts in {time.time() - t0:.0f} s", flush=True)
    tmp = DOC.with_suffix(".md.tmp")
    tmp.write_text(render(statuses))
    tmp.replace(DOC)
    print(f"[run_all] wrote {_relative(DOC)}")


if __name__ == "__main__":
    main()
