"""Which Silverbox test record the rows' nmae should be (``system.score_on``), by the published laws: each record's
free-run envelope over each published Silverbox law (conf/reproduction.yaml, ``score_record``) on the slices of
`make repro`, at the status table's resources. Writes the table to ``score_record.output`` and prints it.

    python benchmarks/score_record.py [root=runs/repro]
"""

import sys
from pathlib import Path

from nsl_hpc.analysis.reproduction import envelope_factors, factor_text, largest_factor, resource_text
from nsl_hpc.config import plain, tool_settings
from nsl_hpc.core.atomic import write_text
from nsl_hpc.sweep import layout


def main() -> None:
    cfg = plain(tool_settings("reproduction", sys.argv[1:]))
    spec = cfg["score_record"]
    lines = ["| published law | slice | record (free run) | outcomes | envelope / law | largest factor |",
             "|---|---|---|---:|---|---:|"]
    for law in spec["laws"]:
        slice_name, at = cfg["laws"][law]["slice"], cfg["laws"][law]["at"]
        sweep_dir = Path(cfg["root"]) / slice_name
        if not (sweep_dir / layout.RESULTS).exists():
            sys.exit(f"error: {sweep_dir}/results.parquet does not exist; run make repro (or that slice) first")
        for record in spec["records"]:
            outcomes, ratios = envelope_factors(sweep_dir, law, at, f"nmae_free_run_{record}")
            cells = ", ".join(f"{resource_text(r)}: {factor_text(x)}" for r, x in zip(at, ratios, strict=True))
            lines.append(f"| {law} | {slice_name} | {record} | {outcomes:,} | {cells} | "
                         f"{factor_text(largest_factor(ratios))} |")
    text = "\n".join(lines) + "\n"
    write_text(text, Path(spec["output"]))
    print(text)


if __name__ == "__main__":
    main()
