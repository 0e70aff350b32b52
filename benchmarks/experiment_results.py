"""Results of ``svolsdf benchmark --experiment`` kept in benchmarks/results/: the run's record
(OUT/experiment.json) copied as NAME.json, with NAME.md (and NAME.png) rendered from it by
`svolsdf.commands.experiment.experiment_markdown` and `experiment_plot`, exactly what the
command writes beside its runs.

    python benchmarks/experiment_results.py --run OUT --results benchmarks/results/NAME.json
    python benchmarks/experiment_results.py --from-json benchmarks/results/NAME.json \
        --results benchmarks/results/NAME.md      # render only (tests/benchmarks)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from svolsdf.commands.experiment import EXPERIMENT_FILE, experiment_markdown, experiment_plot


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="the benchmark's output folder (its experiment.json)")
    ap.add_argument("--results", type=Path, required=True,
                    help="NAME.json to write (with --run) or NAME.md to render (--from-json)")
    ap.add_argument("--from-json", type=Path, help="only render this record's Markdown")
    args = ap.parse_args()
    if args.from_json:
        record = json.loads(args.from_json.read_text())
        args.results.with_suffix(".md").write_text(experiment_markdown(record))
        return
    if args.run is None:
        ap.error("give --run OUT (or --from-json)")
    record = json.loads((args.run / EXPERIMENT_FILE).read_text())
    out = args.results.with_suffix(".json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    record = json.loads(out.read_text())
    out.with_suffix(".md").write_text(experiment_markdown(record))
    experiment_plot(record, out.with_suffix(".png"))
    print(f"wrote {out}, {out.with_suffix('.md')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
