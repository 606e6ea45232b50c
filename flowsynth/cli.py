"""The ``flowsynth`` command: ``flowsynth export``, ``flowsynth preview`` and ``flowsynth stats``.

Every BouncingThingsConfig field is also a flag (``--num-frames 8``, ``--object-size 0.3,1.0``,
``--texture-dir none``); flags override values from ``--config FILE`` (JSON, TOML or YAML).
Exit status: 0 success, 2 bad input (config, flags, conflicting folder), 1 other failures.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from flowsynth.errors import FlowsynthError

__all__ = ["build_config", "main"]


def _convert(text: str, type_str: str):
    t = type_str.replace(" ", "")
    if "|None" in t or "None|" in t:
        if text.lower() in ("none", "null", ""):
            return None
        t = t.replace("|None", "").replace("None|", "")
    if t.startswith("tuple["):
        inner = t[len("tuple["):-1].split(",")[0].replace("...", "")
        return tuple(_convert(x, inner) for x in text.split(",") if x != "")
    if t == "int":
        return int(text)
    if t == "float":
        return float(text)
    if t == "bool":
        return text.lower() in ("1", "true", "yes", "on")
    return text


def _config_fields():
    from flowsynth.config import BouncingThingsConfig

    return dataclasses.fields(BouncingThingsConfig)


def _read_config_file(path: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise FlowsynthError(f"config file {path} does not exist")
    text = p.read_text()
    try:
        if p.suffix == ".json":
            data = json.loads(text)
        elif p.suffix == ".toml":
            import tomllib

            data = tomllib.loads(text)
        elif p.suffix in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError as e:
                raise FlowsynthError("YAML config files need PyYAML: pip install pyyaml (or use JSON/TOML)") from e
            data = yaml.safe_load(text)
        else:
            raise FlowsynthError(f"config file {path}: unknown extension; use .json, .toml or .yaml")
    except (ValueError, TypeError) as e:  # JSONDecodeError, TOMLDecodeError, YAMLError subclasses
        raise FlowsynthError(f"config file {path} is not valid {p.suffix[1:].upper()}: {e}") from e
    except Exception as e:
        if type(e).__module__.startswith("yaml"):
            raise FlowsynthError(f"config file {path} is not valid YAML: {e}") from e
        raise
    if not isinstance(data, dict):
        raise FlowsynthError(f"config file {path} must hold a mapping of config fields")
    return {k.replace("-", "_"): (tuple(v) if isinstance(v, list) else v) for k, v in data.items()}


def build_config(args: argparse.Namespace):
    """BouncingThingsConfig from ``--config FILE`` overridden by explicit field flags."""
    from flowsynth.config import BouncingThingsConfig

    values = _read_config_file(args.config) if args.config else {}
    for f in _config_fields():
        v = getattr(args, "cfg_" + f.name)
        if v is not None:
            values[f.name] = _convert(v, str(f.type))
    return BouncingThingsConfig.from_dict(values)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flowsynth", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    ex = sub.add_parser("export", help="generate N samples into a folder (resumable)")
    ex.add_argument("--out", required=True, help="output folder")
    ex.add_argument("--num", type=int, required=True, help="number of samples")
    ex.add_argument("--seed", type=int, default=0)
    ex.add_argument("--workers", type=int, default=1, help="processes, each generating its own share")
    ex.add_argument("--layout", choices=("native", "flyingchairs"), default="native")
    ex.add_argument("--outputs", default=None, help="comma-separated output keys (default: a useful set)")
    ex.add_argument("--occlusion", choices=("exact", "depth"), default="exact")
    ex.add_argument("--overwrite", action="store_true", help="replace an export of another config")
    ex.add_argument("--no-progress", action="store_true")
    pv = sub.add_parser("preview", help="write a contact sheet PNG of one sample")
    pv.add_argument("--out", required=True, help="PNG file to write")
    pv.add_argument("--index", type=int, default=0)
    pv.add_argument("--seed", type=int, default=0)
    st = sub.add_parser("stats", help="measure flow, occlusion, texture and timing statistics of N samples")
    st.add_argument("--num", type=int, default=16, help="number of samples")
    st.add_argument("--seed", type=int, default=0)
    st.add_argument("--start", type=int, default=0, help="first sample index")
    st.add_argument("--dis", action="store_true", help="also compare OpenCV DIS flow with zero flow (needs opencv)")
    st.add_argument("--json", default=None, help="also write the statistics to this JSON file")
    for sp in (ex, pv, st):
        sp.add_argument("--config", default=None, help="config file (.json, .toml, .yaml)")
        grp = sp.add_argument_group("scene configuration (BouncingThingsConfig fields)")
        for f in _config_fields():
            grp.add_argument("--" + f.name.replace("_", "-"), dest="cfg_" + f.name, default=None,
                             metavar=str(f.type).replace(" ", ""))
    return p


def _preview(args, cfg) -> None:
    from flowsynth.datasets import BouncingThings
    from flowsynth.viz import sample_preview, save_png

    outputs = ["rgb", "flow_fw", "flow_bw", "occ_fw", "depth", "normals", "instance", "box2d_visible",
               "object_valid"]
    ds = BouncingThings(cfg, outputs=outputs if cfg.num_frames > 1 else
                        [k for k in outputs if "_fw" not in k and "_bw" not in k], seed=args.seed)
    img = sample_preview(ds.sample(args.index))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    save_png(args.out, img)
    print(f"wrote {args.out} ({img.shape[1]}x{img.shape[0]})")


def _stats(args, cfg) -> None:
    from flowsynth.io import write_json
    from flowsynth.stats import dataset_stats, format_stats

    st = dataset_stats(cfg, args.num, seed=args.seed, start=args.start, dis=args.dis)
    print(format_stats(st))
    if args.json:
        write_json(Path(args.json), dict(st, config=cfg.to_dict()))
        print(f"wrote {args.json}")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = build_config(args)
        if args.command == "export":
            from flowsynth.export import export

            root = export(cfg, args.out, args.num, seed=args.seed, outputs=args.outputs, workers=args.workers,
                          layout=args.layout, overwrite=args.overwrite, occlusion=args.occlusion,
                          progress=not args.no_progress)
            print(f"exported {args.num} samples to {root}")
        elif args.command == "stats":
            _stats(args, cfg)
        else:
            _preview(args, cfg)
    except (FlowsynthError, ValueError) as e:
        print(f"flowsynth {args.command}: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
