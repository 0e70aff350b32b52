"""How far `svolsdf reconstruct` travels from the command line to the first algorithm, and how
the pipeline reaches the fusion and the mesh.

    python benchmarks/reconstruct_trace.py [--out benchmarks/results/reconstruct_trace.md]

Makes a small synthetic scene, runs ``svolsdf reconstruct SCENE -o OUT --steps 1`` in this
process under `sys.setprofile`, and records the svolsdf call stack (each frame's file and
function, the hops between files) at the first call of the default backbone's algorithm
(`PlaneSweepBackbone.stage`, MVS stage 1), of the fusion (`fuse_depth_maps`) and of the fast
preset's mesh (`poisson_mesh`), which svolsdf files, and which of pipeline/, were entered
before the first algorithm, and every run or load of a stage that does not come from the
runner (`Pipeline._drive`; a stage reaching another one for its input). Run it with
``PYTHONPATH=<checkout>/src`` to measure another commit; nothing is timed.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from _machine import write_results


def trace(work: Path) -> dict:
    import svolsdf
    from svolsdf.cli import main

    root = Path(svolsdf.__file__).resolve().parent
    main(["synth", str(work / "scene"), "--seed", "3", "--size", "96x72"])
    entered: list[str] = []
    found: dict = {}
    targets = {("mvs/planesweep.py", "stage"): "mvs", ("fusion/filter.py", "fuse_depth_maps"):
               "fusion", ("fusion/meshing.py", "poisson_mesh"): "mesh"}

    def rel(frame) -> str | None:
        f = Path(frame.f_code.co_filename)
        try:
            return f.resolve().relative_to(root).as_posix()
        except ValueError:
            return None

    nested: list[str] = []  # a stage run or loaded from somewhere else than the runner's _drive

    def prof(frame, event, arg):
        if event != "call":
            return
        r = rel(frame)
        if r is None:
            return
        name = frame.f_code.co_name
        if (r.startswith("pipeline/stages/") and name in ("run", "load")
                and frame.f_back is not None):
            caller = frame.f_back.f_code.co_name
            if caller != "_drive":
                nested.append(f"{r}:{name} from {rel(frame.f_back)}:{caller}")
        if len(found) == len(targets):
            return
        if "mvs" not in found and r not in entered:
            entered.append(r)
        name = targets.get((r, frame.f_code.co_name))
        if name is not None and name not in found:
            stack, f = [], frame
            while f is not None:
                fr = rel(f)
                if fr is not None:
                    stack.append(f"{fr}:{f.f_code.co_name}")
                f = f.f_back
            found[name] = stack[::-1]

    sys.setprofile(prof)
    try:
        main(["reconstruct", str(work / "scene"), "-o", str(work / "out"), "--steps", "1",
              "--no-progress"])
    except SystemExit:
        pass
    finally:
        sys.setprofile(None)
    out = {"entered": entered, "nested": nested,
           "pipeline_entered": sorted(e for e in entered if e.startswith("pipeline/"))}
    for name in targets.values():
        stack = found.get(name, [])
        files = [s.split(":")[0] for s in stack]
        out[name] = {"stack": stack, "files": sorted(set(files)),
                     "hops": sum(1 for a, b in zip(files, files[1:], strict=False) if a != b)}
    return out


def main_() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--label", default="this checkout")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="svolsdf-trace-") as tmp:
        r = trace(Path(tmp))
    lines = [f"## {args.label}", "",
             f"- svolsdf files entered before the first algorithm: {len(r['entered'])}, of them "
             f"in pipeline/: {len(r['pipeline_entered'])} ({', '.join(r['pipeline_entered'])})",
             f"- stages run by something else than the runner (a stage reaching another "
             f"for its input): {len(r['nested'])}"
             + (f" ({'; '.join(r['nested'])})" if r["nested"] else "")]
    for name, what in (("mvs", "`PlaneSweepBackbone.stage`"), ("fusion", "`fuse_depth_maps`"),
                       ("mesh", "`poisson_mesh`")):
        t = r[name]
        lines += [f"- to {what}: {len(t['stack'])} frames, {t['hops']} hops between files, "
                  f"{len(t['files'])} files", "", "```", *t["stack"], "```"]
    lines.append("")
    text = "\n".join(lines)
    print(text)
    if args.out:
        old = args.out.read_text() if args.out.is_file() else ""
        write_results(args.out, old.split("\n## Notes")[0] + ("\n" if old else "") + text)


if __name__ == "__main__":
    main_()
