"""`gmmap inspect`: fit a log and report encoded bytes against the raw scans."""

from __future__ import annotations

import time

from services.cli_flags import config_flag, fit_flags, keyframe_flags, resolve_config, source_flags
from services.commands.common import progress_bars, read_source


def cmd_inspect(args) -> int:
    import json

    from protocol import encode
    from services.replay import fit_scans, load_fit_kernels, scan_message

    settings = resolve_config(args)
    scans, read = read_source(args, settings)
    dim = scans[0].pose.dim if scans else 2
    config = settings.fit.for_dimension(dim)
    start, bars = progress_bars()
    # fit_s: wall seconds of fitting alone (numba threads as NUMBA_NUM_THREADS sets them), with the
    # fit's kernels loaded first, as a running agent has them (kernels_s).
    kernels_s = load_fit_kernels(scans[0], config) if scans else 0.0
    fit_start = time.perf_counter()
    models = fit_scans(scans, config, start("fit", len(scans)))
    fit_s = time.perf_counter() - fit_start
    for bar in bars:
        bar.close()
    sizes = [len(encode(scan_message(m, s), args.encoding)) for m, s in zip(models, scans)]
    # Raw: float32 per beam in 2D (ranges), float32 x, y, z per point in 3D.
    raw = [4 * (len(s.hits) + len(s.no_return)) * (1 if dim == 2 else 3) for s in scans]
    components = sum(m.n_components for m in models)
    report = {
        "scans": len(scans),  # after keyframing
        "scans_read": read,
        "dimension": dim,
        "encoding": args.encoding,
        "components": components,
        "fit_s": fit_s,
        "kernels_s": kernels_s,
        "bytes": sum(sizes),
        "raw_bytes": sum(raw),
        "bytes_per_component": sum(sizes) / max(components, 1),
        "bytes_per_scan": sum(sizes) / max(len(scans), 1),
        "raw_bytes_per_scan": sum(raw) / max(len(scans), 1),
        "ratio_to_raw": sum(sizes) / max(sum(raw), 1),
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key:>20}: {value:.2f}" if isinstance(value, float) else f"{key:>20}: {value}")
    return 0


def add_inspect(sub) -> None:
    p = sub.add_parser("inspect", help="fit a log and report encoded bytes against the raw scans")
    source_flags(p)
    keyframe_flags(p)
    p.add_argument("--encoding", choices=["q", "f32"], default="q")
    fit_flags(p)
    p.add_argument("--json", action="store_true")
    config_flag(p)
    p.set_defaults(run=cmd_inspect)
