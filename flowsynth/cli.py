"""The ``flowsynth`` command: ``flowsynth export``, ``flowsynth preview``, ``flowsynth stats`` and ``flowsynth tune``.

Every BouncingThingsConfig field is also a flag (``--num-frames 8``, ``--object-size 0.3,1.0``,
``--texture-dir none``); flags override values from ``--config FILE`` (JSON, TOML or YAML), which override
``--preset NAME`` (default, chairs, things; flowsynth.scene.config.PRESETS). ``--dataset layers`` makes
FlyingChairs-style 2D layers instead (flowsynth.datasets.Layers): a LayersConfig from ``--config FILE`` and the
flags of its fields (``--width``, ``--height``, ``--num-frames``, ``--texture-dir``, ``--motion-scale``, ...).
``--mixture FILE`` takes a mixture preset instead (what ``flowsynth tune`` writes): the stream is
``flowsynth.datasets.Mixture.from_preset(FILE, outputs, seed)``, and the file alone sets the configs (no config flags;
``--width``, ``--height`` and ``--num-frames`` only when they equal the file's).
``flowsynth export --help`` lists every flag with its type, default and meaning (from the field
docstrings in flowsynth/scene/config.py).

Exit status:
  0    success.
  1    an unexpected failure: a bug in flowsynth, not your input. The traceback is printed; please report
       it. (Any exception that is not a flowsynth error, a ValueError from numpy or torch included.)
  2    bad input: a flag or config value, a config file, an output folder that holds something else,
       or a sample too large for the memory (flowsynth's own errors: ConfigError, AssetError,
       ExportError...); nothing was written.
  3    reading or writing files failed (disk full, permission denied, ...); samples already finished
       are kept, temporaries removed: free space and re-run the same command to resume.
  130  interrupted (Ctrl-C); re-run the same command to resume.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import time
import traceback
from pathlib import Path

from flowsynth._flags import SIZE_FIELDS, add_config_flags, add_layers_flags, integer, layers_only_fields
from flowsynth.errors import ConfigError, FlowsynthError, StorageError

__all__ = ["PREVIEW_BOUNCING", "PREVIEW_LAYERS", "build_config", "main"]

PREVIEW_BOUNCING = ("rgb", "flow_fw", "flow_bw", "occ_fw", "depth", "normals", "instance", "box2d_visible",
                    "object_valid")
"""What ``flowsynth preview`` shows of a BouncingThings sample without ``--outputs``."""
PREVIEW_LAYERS = ("rgb", "flow_fw", "flow_bw", "valid_fw", "occ_fw", "occ_bw", "instance")
"""What it shows of a Layers sample (``--dataset layers``), and of a mixture with a Layers source."""


def _config_fields():
    from flowsynth.scene import BouncingThingsConfig

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


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def build_config(args: argparse.Namespace):
    """BouncingThingsConfig from ``--preset NAME``, overridden by ``--config FILE``, then by field flags; with
    ``--dataset layers`` a LayersConfig from ``--config FILE``, then its fields' flags; with ``--mixture FILE`` the
    file's MixtureConfig."""
    from flowsynth.scene import BouncingThingsConfig

    from flowsynth.scene import PRESETS

    if args.mixture is not None:
        return _mixture_config(args)
    layers_given = [_flag(f.name) for f in layers_only_fields() if getattr(args, "layers_" + f.name) is not None]
    if args.dataset == "layers":
        return _layers_config(args)
    if layers_given:
        raise ConfigError(f"{', '.join(layers_given)}: flags of 2D layers; add --dataset layers or leave them out")
    preset = "default" if args.preset is None else args.preset
    if preset not in PRESETS:
        raise ConfigError(f"--preset: unknown preset {preset!r}; presets: {sorted(PRESETS)}")
    values = dict(PRESETS[preset])
    values.update(_read_config_file(args.config) if args.config else {})
    flags = {f.name: getattr(args, "cfg_" + f.name) for f in _config_fields()}
    values.update({k: v for k, v in flags.items() if v is not None})  # parsed by flowsynth._flags
    try:
        return BouncingThingsConfig.from_dict(values)
    except ConfigError as e:  # messages start with the field name; name the flag when one set it
        name = re.match(r"\w*", str(e)).group(0)
        if flags.get(name) is not None:
            raise ConfigError(f"--{name.replace('_', '-')}: {e}") from e
        raise


def _mixture_config(args: argparse.Namespace):
    """The MixtureConfig of ``--mixture FILE``; ConfigError naming a flag that would set what the file sets, or a
    size flag that differs from the file's."""
    from flowsynth.datasets import MixtureConfig

    if args.dataset is not None:
        raise ConfigError(f"--dataset {args.dataset}: a mixture preset names its sources' kinds; leave --dataset out "
                          "with --mixture")
    size = {_flag(n): getattr(args, "cfg_" + n) for n in SIZE_FIELDS}
    given = ["--preset"] * (args.preset is not None) + ["--config"] * (args.config is not None)
    given += [_flag(f.name) for f in _config_fields() if f.name not in SIZE_FIELDS
              and getattr(args, "cfg_" + f.name) is not None]
    given += [_flag(f.name) for f in layers_only_fields() if getattr(args, "layers_" + f.name) is not None]
    if given:
        raise ConfigError(f"{', '.join(given)}: the mixture preset {args.mixture} sets every source's config; leave "
                          f"{'it' if len(given) == 1 else 'them'} out with --mixture (or edit the file)")
    try:
        cfg = MixtureConfig.from_file(args.mixture)
    except ConfigError as e:
        raise ConfigError(f"--mixture: {e}") from e
    wrong = [f"{flag} {v}" for (flag, v), n in zip(size.items(), SIZE_FIELDS) if v is not None and v != getattr(cfg, n)]
    if wrong:
        raise ConfigError(f"{', '.join(wrong)}: the mixture preset {args.mixture} makes samples of --width "
                          f"{cfg.width} --height {cfg.height} --num-frames {cfg.num_frames}; leave the size flags out "
                          "with --mixture (or edit the file)")
    return cfg


def _layers_config(args: argparse.Namespace):
    """LayersConfig from ``--config FILE``, overridden by its fields' flags (module docstring)."""
    from flowsynth.datasets import LayersConfig

    if args.preset is not None:
        raise ConfigError("--preset names a BouncingThings preset; --dataset layers takes --config FILE and its flags")
    names = {f.name for f in dataclasses.fields(LayersConfig)}
    scene_only = [_flag(f.name) for f in _config_fields() if f.name not in names
                  and getattr(args, "cfg_" + f.name) is not None]
    if scene_only:
        raise ConfigError(f"{', '.join(scene_only)}: not a field of 2D layers (LayersConfig: "
                          f"{', '.join(_flag(n) for n in sorted(names))}); leave it out or drop --dataset layers")
    flags = {n: getattr(args, "cfg_" + n, None) for n in names}
    flags.update({f.name: getattr(args, "layers_" + f.name) for f in layers_only_fields()})
    values = _read_config_file(args.config) if args.config else {}
    values.update({k: v for k, v in flags.items() if v is not None})
    try:
        return LayersConfig.from_dict(values)
    except ConfigError as e:
        name = re.match(r"\w*", str(e)).group(0)
        if flags.get(name) is not None:
            raise ConfigError(f"{_flag(name)}: {e}") from e
        raise


def _parser() -> argparse.ArgumentParser:
    from flowsynth.io import layouts
    from flowsynth.io.layouts.webdataset import DEFAULT_SHARD_SIZE
    from flowsynth.plan import OCCLUSION_METHODS

    _sub_kw = {"epilog": "exit status:\n" + __doc__.split("Exit status:\n")[1].rstrip(),
               "formatter_class": argparse.RawDescriptionHelpFormatter}
    p = argparse.ArgumentParser(prog="flowsynth", description=__doc__.split("\n")[0], **_sub_kw)
    sub = p.add_subparsers(dest="command", required=True)
    ex = sub.add_parser("export", help="generate N samples into a folder (resumable)", **_sub_kw,
                        usage="flowsynth export --out DIR --num N [options]  (all options: flowsynth export --help)")
    ex.add_argument("--out", required=True, help="output folder (created; re-running resumes) [required]")
    ex.add_argument("--num", type=integer, required=True, help="number of samples [int, required]")
    ex.add_argument("--seed", type=integer, default=0, help="sample i depends on (seed, i) [int, default 0]")
    ex.add_argument("--workers", type=integer, default=None,
                    help="local engine: processes, each making its own share [int, default 1]; ray engine: actors, "
                         "one CPU each [int, default one per CPU of the cluster]")
    ex.add_argument("--engine", choices=("local", "ray"), default="local",
                    help="where samples are made: this machine, or a Ray cluster (needs the ray extra: "
                         "pip install 'flowsynth[ray]'; docs/distributed.md) [default local]")
    ex.add_argument("--address", default=None,
                    help="ray engine: the cluster to join (auto, HOST:6379, ray://HOST:10001); --out must be a "
                         "folder every node reaches [default: the cluster this process joined, else a local one]")
    ex.add_argument("--layout", choices=layouts.names(), default="native",
                    help="files on disk; " + "; ".join(f"{n}: {layouts.get(n).summary}" for n in layouts.names())
                    + " [default native]")
    ex.add_argument("--shard-size", type=integer, default=None,
                    help="layouts that write shards (webdataset): samples per shard, also the unit a worker "
                         f"writes and a resume rewrites [int, default {DEFAULT_SHARD_SIZE}]")
    ex.add_argument("--outputs", default=None, help="comma-separated output keys [default: the layout's set]")
    ex.add_argument("--exr-compression", choices=layouts.EXR_COMPRESSIONS, default="zip",
                    help="lossless compression of EXR files (sizes and times: benchmarks/speed/export.py) "
                         "[default zip]")
    ex.add_argument("--dry-run", action="store_true",
                    help="print the bytes each output costs per sample and in total; write nothing [flag, default off]")
    ex.add_argument("--occlusion", choices=OCCLUSION_METHODS, default="exact",
                    help="occ_* by exact visibility rays or a depth-buffer test (BouncingThings sources; part of the "
                         "export's identity, so a resume keeps it) [default exact]")
    ex.add_argument("--verify", action="store_true",
                    help="on resume, check every file's sha256 against the manifest, not only presence and size "
                         "[flag, default off]")
    ex.add_argument("--overwrite", action="store_true",
                    help="replace an export of another config in --out [flag, default off]")
    ex.add_argument("--no-progress", action="store_true", help="no progress bar [flag, default off]")
    pv = sub.add_parser("preview", help="write a contact sheet PNG of one sample", **_sub_kw,
                        usage="flowsynth preview --out FILE.png [options]  (all options: flowsynth preview --help)")
    pv.add_argument("--out", required=True, help="PNG file to write [required]")
    pv.add_argument("--index", type=integer, default=0, help="sample index [int, default 0]")
    pv.add_argument("--seed", type=integer, default=0, help="dataset seed [int, default 0]")
    pv.add_argument("--outputs", default=None,
                    help="comma-separated output keys to show [default: rgb, flow, occlusion, depth, ids, boxes]")
    st = sub.add_parser("stats", help="measure flow, occlusion, texture and timing statistics of N samples",
                        **_sub_kw, usage="flowsynth stats [options]  (all options: flowsynth stats --help)")
    st.add_argument("--num", type=integer, default=16, help="number of samples [int, default 16]")
    st.add_argument("--seed", type=integer, default=0, help="dataset seed [int, default 0]")
    st.add_argument("--start", type=integer, default=0, help="first sample index [int, default 0]")
    st.add_argument("--dis", action="store_true",
                    help="also compare OpenCV DIS flow with zero flow (needs opencv) [flag, default off]")
    st.add_argument("--json", default=None, help="also write the statistics to this JSON file [default: none]")
    _tune_parser(sub, _sub_kw)
    for sp in (ex, pv, st):
        sp.add_argument("--mixture", default=None, metavar="FILE",
                        help="a mixture preset file (JSON; flowsynth tune writes one): the samples of "
                             "flowsynth.datasets.Mixture.from_preset(FILE, outputs, seed); takes no --dataset, "
                             "--preset, --config or config flags [default: none]")
        sp.add_argument("--dataset", choices=("bouncing", "layers"), default=None,
                        help="what to generate: bouncing (3D scenes, BouncingThings) or layers (FlyingChairs-style 2D "
                             "layers, flowsynth.datasets.Layers: a LayersConfig from --config and the flags of its "
                             "fields) [default bouncing]")
        sp.add_argument("--preset", default=None,
                        help="named config to start from: default, chairs, things (BouncingThingsConfig.preset) "
                             "[default: default]")
        sp.add_argument("--config", default=None,
                        help="config file (.json, .toml, .yaml); overrides the preset, flags override it "
                             "[default: none]")
        add_config_flags(sp)
        add_layers_flags(sp)
    return p


def _tune_parser(sub, sub_kw: dict) -> None:
    from flowsynth.training import PRECISIONS
    from flowsynth.tune import DEFAULT_BUDGET, DEFAULT_CANDIDATES, QUICK, RECIPE

    tn = sub.add_parser("tune", help="fit the generator's knobs to your validation pairs (docs/tune.md; resumable)",
                        **sub_kw, usage="flowsynth tune --val DIR --out PRESET.json [options]")
    tn.add_argument("--val", required=True,
                    help="folder of validation pairs with true flow: Middlebury (NAME/frame10.png, frame11.png, "
                         "flow10.flo), FlyingChairs (*_img1.ppm, *_img2.ppm, *_flow.flo), KITTI (image_2/, "
                         "flow_occ/) or Sintel (clean|final/SCENE/, flow/SCENE/) [required]")
    tn.add_argument("--out", required=True,
                    help="the preset file to write: a mixture preset (fs.datasets.Mixture.from_preset reads it); "
                         "state and report go to PRESET.tune/ beside it; re-running resumes [required]")
    tn.add_argument("--pairs", default=None, help="comma-separated names (or globs) of the pairs to tune on "
                                                  "[default: all]")
    tn.add_argument("--budget", type=integer, default=None,
                    help=f"training steps over all nets (one step: one net, one batch of {RECIPE.batch} crops) "
                         f"[int, default {DEFAULT_BUDGET}; --quick: the smallest that trains the candidates]")
    tn.add_argument("--candidates", type=integer, default=None,
                    help=f"points of the search space tried, the default among them [int, default "
                         f"{DEFAULT_CANDIDATES}; --quick: 2]")
    tn.add_argument("--pool", type=integer, default=None,
                    help=f"training pairs rendered per net [int, default {RECIPE.pool}; --quick: {QUICK.pool}]")
    tn.add_argument("--seed", type=integer, default=0,
                    help="candidates drawn, nets, pools and batches [int, default 0]")
    tn.add_argument("--device", default="cpu", help="torch device the nets train on (cpu, cuda, ...) [default cpu]")
    tn.add_argument("--precision", choices=PRECISIONS, default="fp32",
                    help="training precision; fp16 needs CUDA [default fp32]")
    tn.add_argument("--workers", type=integer, default=0,
                    help="processes rendering the training pools [int, default 0: this one]")
    tn.add_argument("--quick", action="store_true",
                    help="a tiny recipe that checks a tune runs; its winner means little [flag, default off]")
    tn.add_argument("--no-resource-check", action="store_true",
                    help="go on when the memory and disk the tune needs (estimated before any work, docs/tune.md) "
                         "are more than this machine has [flag, default off: refused, exit 2]")


def _tune(args) -> None:
    from flowsynth.tune import tune, work_dir

    rep = tune(args.val, args.out, pairs=None if args.pairs is None else [p for p in args.pairs.split(",") if p],
               budget=args.budget, candidates=args.candidates, pool=args.pool, seed=args.seed, device=args.device,
               precision=args.precision, workers=args.workers, quick=args.quick,
               check_resources=not args.no_resource_check)
    print(f"wrote {args.out} ({rep['winner']}); {rep['verdict']}; report: {work_dir(args.out) / 'report.md'}")


def _preview(args, cfg) -> None:
    from flowsynth.datasets import config_kind, make_stream
    from flowsynth.memory import check_sample_memory
    from flowsynth.viz import sample_preview, save_png

    kind = config_kind(cfg)
    kinds = {config_kind(c) for _, c in cfg.sources} if kind == "mixture" else {kind}
    outputs = _outputs(args) or (list(PREVIEW_LAYERS) if "layers" in kinds else list(PREVIEW_BOUNCING))
    check_sample_memory(cfg)
    ds = make_stream(cfg, outputs if cfg.num_frames > 1 else
                     [k for k in outputs if "_fw" not in k and "_bw" not in k], seed=args.seed)
    sample = ds.sample(args.index)
    # what made the picture, so a stale one can be told apart (scripts/make_preview.py, tests/test_cli.py)
    text = {"flowsynth:config": json.dumps(cfg.to_dict(), sort_keys=True), "flowsynth:seed": str(args.seed),
            "flowsynth:index": str(args.index)}
    title = None
    if kind != "bouncing":
        text["flowsynth:dataset"] = kind
    if kind == "mixture":
        name, src = cfg.sources[int(sample["source"])]
        text["flowsynth:source"] = name
        title = f"sample {args.index} of {Path(args.mixture).name}: source {name!r} ({config_kind(src)})"
    img = sample_preview(sample, title=title)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    save_png(args.out, img, text=text)
    print(f"wrote {args.out} ({img.shape[1]}x{img.shape[0]})")


def _outputs(args) -> list[str] | None:
    """The keys of ``--outputs`` (comma-separated), None when it is not given."""
    return None if args.outputs is None else [k for k in args.outputs.split(",") if k]


def _dry_run(args, cfg) -> None:
    from flowsynth.export import estimate

    sizes = estimate(cfg, args.num, seed=args.seed, outputs=_outputs(args), layout=args.layout,
                     occlusion=args.occlusion, exr_compression=args.exr_compression, shard_size=args.shard_size)
    rows = [(k, v, v * args.num) for k, v in sorted(sizes.per_sample.items(), key=lambda kv: -kv[1])]
    if sizes.index:
        rows.append(("(index files)", 0, sizes.index))
    rows.append(("total", sum(sizes.per_sample.values()), sizes.total))
    print(f"{'output':<16} {'bytes/sample':>14} {f'bytes x {args.num}':>16}")
    for name, one, total in rows:
        print(f"{name:<16} {one:>14,} {total:>16,}")
    print(f"dry run: nothing written; layout {args.layout}, sizes measured on sample 0 "
          f"(other samples compress a few per cent differently)")


def _export(args, cfg) -> None:
    from flowsynth.export import export_dataset
    from flowsynth.io import layouts

    start = time.perf_counter()
    root = export_dataset(cfg, args.out, args.num, seed=args.seed, outputs=_outputs(args), workers=args.workers,
                          layout=args.layout, overwrite=args.overwrite, occlusion=args.occlusion,
                          exr_compression=args.exr_compression, verify=args.verify, progress=not args.no_progress,
                          engine=args.engine, address=args.address, shard_size=args.shard_size)
    run = json.loads((Path(root) / "manifest.json").read_text())["run"]
    print(f"{root} holds {args.num} sample{'s' if args.num != 1 else ''}: {run['present']} present (whole), "
          f"{run['written']} written ({run['repaired']} of them repaired) in {time.perf_counter() - start:.1f} s, "
          f"layout {args.layout}; load it in Python with {layouts.get(args.layout).load_hint(root)}")


def _stats(args, cfg) -> None:
    from flowsynth.io import write_json
    from flowsynth.memory import check_sample_memory
    from flowsynth.stats import dataset_stats, format_stats

    check_sample_memory(cfg)
    st = dataset_stats(cfg, args.num, seed=args.seed, start=args.start, dis=args.dis)
    print(format_stats(st))
    if args.json:
        write_json(Path(args.json), dict(st, config=cfg.to_dict()))
        print(f"wrote {args.json}")


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status (module docstring)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a flag that does not parse (2); argparse printed why
        return e.code if isinstance(e.code, int) else 2
    try:
        cfg = None if args.command == "tune" else build_config(args)
        if args.command == "tune":
            _tune(args)
        elif args.command == "export" and args.dry_run:
            _dry_run(args, cfg)
        elif args.command == "export":
            _export(args, cfg)
        elif args.command == "stats":
            _stats(args, cfg)
        else:
            _preview(args, cfg)
    except StorageError as e:
        print(f"flowsynth {args.command}: error: {e}", file=sys.stderr)
        return 3
    except FlowsynthError as e:  # flowsynth's own errors only: a ValueError from elsewhere is a bug, not bad input
        print(f"flowsynth {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"flowsynth {args.command}: interrupted; re-run the same command to resume", file=sys.stderr)
        return 130
    except Exception:
        traceback.print_exc()
        print(f"flowsynth {args.command}: internal error (exit status 1): a bug in flowsynth, not in your input; "
              "please report it with the traceback above", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
