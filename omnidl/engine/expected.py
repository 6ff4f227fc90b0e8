"""The end-of-run summary lines: the final validation metrics, next to the expected range when the run uses the
configuration that range was measured for (``expected`` in ``configs/train.yaml``)::

    expected:
      when: {model.name: fredsnet, trainer.seed: 0, ...}   # config keys (dotted) the range was measured with
      seeds: "0, 1"                                         # free text: what the range covers
      metrics: {val/delta1: [0.2, 0.4], ...}                # [low, high] per metric
"""
from __future__ import annotations

from omegaconf import DictConfig, OmegaConf


def expected_ranges(cfg: DictConfig) -> dict[str, tuple[float, float]] | None:
    """``{metric: (low, high)}`` when every ``expected.when`` key of ``cfg`` has the listed value, else None."""
    spec = cfg.get("expected")
    if not spec or not spec.get("metrics"):
        return None
    for key, value in (spec.get("when") or {}).items():
        if OmegaConf.select(cfg, key, default="<unset>") != value:
            return None
    return {k: (float(v[0]), float(v[1])) for k, v in spec.metrics.items()}


def summary_lines(final: dict[str, float], cfg: DictConfig) -> list[str]:
    """One line per metric: value, and ``expected [lo, hi]`` (``OUTSIDE`` when it is not) for the default run."""
    ranges = expected_ranges(cfg)
    keys = [k for k in final if not k.startswith("val/loss_")]
    if not keys:
        return []
    width = max(len(k) for k in keys)
    lines = []
    if ranges:
        seeds = (cfg.expected.get("seeds") or "").strip()
        lines.append(f"final validation metrics; expected range of this default run ({seeds}):")
    else:
        lines.append("final validation metrics:")
    for k in keys:
        line = f"  {k:<{width}}  {final[k]:.4g}"
        if ranges and k in ranges:
            lo, hi = ranges[k]
            line += f"   expected [{lo:.4g}, {hi:.4g}]" + ("" if lo <= final[k] <= hi else "  OUTSIDE")
        lines.append(line)
    return lines


def ranges_from_runs(finals: list[dict[str, float]], margin: float = 0.1) -> dict[str, list[float]]:
    """``{metric: [low, high]}`` covering the final metrics of several runs (e.g. seeds), widened by their spread
    and by ``margin`` of the value (machines differ in the last digits)."""
    out = {}
    for k in finals[0]:
        if k.startswith("val/loss_"):
            continue
        vals = [float(f[k]) for f in finals if k in f]
        lo, hi = min(vals), max(vals)
        pad = max(hi - lo, margin * max(abs(lo), abs(hi)))
        low, high = lo - pad, hi + pad
        if 0 <= lo and hi <= 1:  # a fraction stays in [0, 1]
            low, high = max(low, 0.0), min(high, 1.0)
        out[k] = [round(low, 4), round(high, 4)]
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m omnidl.engine.expected [--margin F] RUN_DIR...``: the ``expected.metrics`` block for
    configs/train.yaml from the ``metrics.json`` of finished default runs (``--margin``: relative padding, 0.1)."""
    import json
    import sys
    from pathlib import Path
    dirs = list(sys.argv[1:] if argv is None else argv)
    margin = 0.1
    if dirs[:1] == ["--margin"] and len(dirs) > 1:
        margin, dirs = float(dirs[1]), dirs[2:]
    if not dirs:
        print("usage: python -m omnidl.engine.expected [--margin F] RUN_DIR [RUN_DIR ...]", file=sys.stderr)
        return 2
    finals = []
    for d in dirs:
        path = Path(d) / "metrics.json"
        if not path.is_file():
            print(f"{path} does not exist (not a finished run folder)", file=sys.stderr)
            return 2
        finals.append(json.loads(path.read_text())["final"])
    print("  metrics:")
    for k, (lo, hi) in ranges_from_runs(finals, margin).items():
        print(f"    {k}: [{lo}, {hi}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
