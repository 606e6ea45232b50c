"""The ``flowsynth`` command: ``flowsynth export``, ``flowsynth preview``, ``flowsynth stats`` and ``flowsynth tune``.

Every BouncingThingsConfig field is also a flag (``--num-frames 8``, ``--object-size 0.3,1.0``,
``--texture-dir none``); flags override values from ``--config FILE`` (JSON, TOML or YAML), which override
``--preset NAME`` (default, chairs, things; flowsynth.scene.config.PRESETS). ``--dataset layers`` makes
FlyingChairs-style 2D layers instead (flowsynth.datasets.Layers): a LayersConfig from ``--config FILE`` and the
flags of its fields (``--width``, ``--height``, ``--num-frames``, ``--texture-dir``, ``--motion-scale``, ...).
``--mixture FILE`` takes a mixture preset instead (what ``flowsynth tune`` writes): the stream is
``flowsynth.datasets.Mixture.from_preset(FILE, outputs, seed)``, and the file alone sets the configs (no config flags;
``--width``, ``--height`` and ``--num-frames`` only when they equal the file's).
``flowsynth export --help`` is short; ``flowsynth export --help-fields`` lists every flag with its type, default and
meaning (from the field docstrings in flowsynth/scene/config.py). ``--print-config`` prints the resolved config as
JSON that ``--config`` reads back; ``flowsynth --version`` the version.

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
import difflib
import json
import re
import sys
import textwrap
import time
import traceback
from pathlib import Path

from flowsynth._flags import SIZE_FIELDS, add_config_flags, add_layers_flags, integer, layers_only_fields
from flowsynth.errors import ConfigError, DependencyError, FlowsynthError, StorageError

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
            try:
                import tomllib
            except ImportError as e:  # Python 3.10: tomllib is 3.11's
                raise DependencyError(f"config file {path}: TOML needs Python 3.11 or newer (tomllib); write the "
                                      "config as JSON or YAML on this Python") from e
            data = tomllib.loads(text)
        elif p.suffix in (".yaml", ".yml"):
            try:
                import yaml
            except ImportError as e:
                raise DependencyError(f"config file {path}: YAML needs PyYAML, a dependency of flowsynth that is "
                                      "missing here: pip install pyyaml (or write the config as JSON or TOML)") from e
            data = yaml.safe_load(text)
        else:
            raise FlowsynthError(f"config file {path}: unknown extension; use .json, .toml or .yaml")
    except (ValueError, TypeError) as e:  # JSONDecodeError, TOMLDecodeError, YAMLError subclasses
        raise FlowsynthError(f"config file {path} is not valid {p.suffix[1:].upper()}: {e}") from e
    except Exception as e:
        if type(e).__module__.startswith("yaml"):
            raise FlowsynthError(f"config file {path} is not valid YAML: {e}") from e
        raise
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise FlowsynthError(f"config file {path} must hold a mapping of config field names to values")
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


_EXIT_LINE = textwrap.fill("exit status: 0 done; 1 a bug in flowsynth (traceback printed); 2 bad input, nothing "
                           "written; 3 a file could not be read or written; 130 interrupted (flowsynth --help)", 79)
_FIELDS_HINT = ("Every config field is a flag as well (--width 512, --object-size 0.3,1.0, --texture-dir none): "
                "flowsynth {cmd} --help-fields lists them with their types, defaults and meanings.")


def _paragraphs(*texts: str) -> str:
    """Help text of a few paragraphs, each wrapped to 79 columns (the raw formatter keeps what it is given)."""
    return "\n".join(textwrap.fill(t, 79, break_on_hyphens=False) for t in texts)


class _HelpFields(argparse.Action):
    """``--help-fields``: print the subcommand's full help, every config field flag included, and exit 0."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        command = parser.prog.split()[-1]
        _parsers(fields=True)[1][command].print_help()
        parser.exit()


def _version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("flowsynth")
    except importlib.metadata.PackageNotFoundError:
        return "(not installed: no version)"


def _parser(fields: bool = False) -> argparse.ArgumentParser:
    """The ``flowsynth`` parser. Every config field is a flag of export, preview and stats; ``fields`` documents
    them in the subcommands' help (``--help-fields``), which otherwise stays short."""
    return _parsers(fields)[0]


def _parsers(fields: bool = False) -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The ``flowsynth`` parser (:func:`_parser`) and its subcommands' parsers by name."""
    from flowsynth.io import layouts
    from flowsynth.io.layouts.webdataset import DEFAULT_SHARD_SIZE
    from flowsynth.plan import OCCLUSION_METHODS

    raw = argparse.RawDescriptionHelpFormatter
    p = argparse.ArgumentParser(
        prog="flowsynth", formatter_class=raw, epilog="exit status:\n" + __doc__.split("Exit status:\n")[1].rstrip(),
        description=_paragraphs("Synthetic optical-flow data: export a dataset, preview a sample, measure "
                                "statistics, or tune the generator to your validation pairs.",
                                "Start with: flowsynth preview --out sample.png; then flowsynth export --out DIR "
                                "--num 8 --config examples/config.yaml"))
    p.add_argument("--version", action="version", version=f"flowsynth {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="{export,preview,stats,tune}")
    kw = {"formatter_class": raw, "epilog": _EXIT_LINE}
    ex = sub.add_parser("export", help="generate N samples into a folder (resumable)", **kw,
                        usage="flowsynth export --out DIR --num N [options]",
                        description=_paragraphs("Generate N samples into a folder; the same command again "
                                                "resumes.", _FIELDS_HINT.format(cmd="export")))
    ex.add_argument("--out", metavar="DIR", help="output folder (created; re-running resumes) "
                    "[required]")
    ex.add_argument("--num", type=integer, metavar="N", help="number of samples [int, required]")
    pv = sub.add_parser("preview", help="write a contact sheet PNG of one sample", **kw,
                        usage="flowsynth preview --out FILE.png [options]",
                        description=_paragraphs("Write a contact sheet PNG of one sample: its images, flow, "
                                                "occlusion, depth, ids and boxes.", _FIELDS_HINT.format(cmd="preview")))
    pv.add_argument("--out", metavar="FILE.png", help="PNG file to write [required]")
    pv.add_argument("--index", type=integer, default=0, metavar="I", help="sample index [int, default 0]")
    pv.add_argument("--outputs", default=None, metavar="KEYS",
                    help="comma-separated output keys to show [default: rgb, flow, occlusion, depth, ids, boxes]")
    st = sub.add_parser("stats", help="measure flow, occlusion, texture and timing statistics of N samples", **kw,
                        usage="flowsynth stats [options]",
                        description=_paragraphs("Measure flow, occlusion, texture and timing statistics of N "
                                                "samples.", _FIELDS_HINT.format(cmd="stats")))
    st.add_argument("--num", type=integer, default=16, metavar="N", help="number of samples [int, default 16]")
    st.add_argument("--start", type=integer, default=0, metavar="I", help="first sample index [int, default 0]")
    st.add_argument("--dis", action="store_true",
                    help="also compare OpenCV DIS flow with zero flow (needs opencv) [flag, default off]")
    st.add_argument("--json", default=None, metavar="FILE",
                    help="also write the statistics to this JSON file [default: none]")
    for sp in (ex, pv, st):
        what = sp.add_argument_group("what to generate")
        what.add_argument("--config", default=None, metavar="FILE",
                          help="a .json, .toml or .yaml file (examples/config.yaml); flags override it "
                               "[default: none]")
        what.add_argument("--preset", default=None, metavar="NAME",
                          help="default, chairs or things [default: default]")
        what.add_argument("--dataset", choices=("bouncing", "layers"), default=None, metavar="KIND",
                          help="bouncing (3D scenes) or layers (FlyingChairs-style 2D) [default bouncing]")
        what.add_argument("--mixture", default=None, metavar="FILE",
                          help="a preset of flowsynth tune, instead of --dataset, --preset, --config and field "
                               "flags [default: none]")
        what.add_argument("--seed", type=integer, default=0, metavar="S",
                          help="sample i depends on (seed, i) only [int, default 0]")
        what.add_argument("--print-config", action="store_true",
                          help="print the resolved config as JSON that --config (--mixture for a mixture) reads "
                               "back; exit [flag, default off]")
        what.add_argument("--help-fields", action=_HelpFields, help="also list every config field flag; exit")
        add_config_flags(sp, documented=fields)
        add_layers_flags(sp, documented=fields)
    out = ex.add_argument_group("files and running")
    if fields:  # what each layout writes, one paragraph each, above the exit status
        ex.epilog = "layouts:\n" + "\n".join(textwrap.fill(f"{n}: {layouts.get(n).summary}", 79, initial_indent="  ",
                                                           subsequent_indent="    ", break_long_words=False,
                                                           break_on_hyphens=False) for n in layouts.names()) \
            + "\n\n" + _EXIT_LINE
    out.add_argument("--layout", choices=layouts.names(), default="native", metavar="NAME",
                     help=", ".join(layouts.names()) + f" ({'below' if fields else '--help-fields'} says what each "
                          "writes) [default native]")
    out.add_argument("--outputs", default=None, metavar="KEYS",
                     help="comma-separated output keys [default: the layout's]")
    out.add_argument("--occlusion", choices=OCCLUSION_METHODS, default="exact", metavar="HOW",
                     help="occ_* by exact visibility rays or a depth-buffer test: " + " or ".join(OCCLUSION_METHODS)
                          + " (BouncingThings sources; a resume keeps it) [default exact]")
    out.add_argument("--exr-compression", choices=layouts.EXR_COMPRESSIONS, default="zip", metavar="NAME",
                     help=", ".join(layouts.EXR_COMPRESSIONS) + " (all lossless) [default zip]")
    out.add_argument("--shard-size", type=integer, default=None, metavar="N",
                     help=f"webdataset: samples per shard [int, default {DEFAULT_SHARD_SIZE}]")
    out.add_argument("--dry-run", action="store_true",
                     help="print the bytes per output and in total; write nothing [flag, default off]")
    out.add_argument("--workers", type=integer, default=None, metavar="N",
                     help="processes (local) or actors (ray) [int, default 1; ray: one per CPU]")
    out.add_argument("--engine", choices=("local", "ray"), default="local",
                     help="ray needs flowsynth[ray] [default local]")
    out.add_argument("--address", default=None,
                     help="ray: the cluster to join (auto, HOST:6379, ray://HOST:10001) [default: the joined one, "
                          "else local]")
    out.add_argument("--verify", action="store_true",
                     help="on resume, check each file's sha256 [flag, default off]")
    out.add_argument("--overwrite", action="store_true",
                     help="replace an export of another config in --out [flag, default off]")
    out.add_argument("--no-progress", action="store_true", help="no progress bar [flag, default off]")
    tn = _tune_parser(sub, kw)
    return p, {"export": ex, "preview": pv, "stats": st, "tune": tn}


def _tune_parser(sub, sub_kw: dict) -> argparse.ArgumentParser:
    from flowsynth.train.steps import PRECISIONS
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
    return tn


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


def _parse(argv: list[str] | None) -> argparse.Namespace:
    """The parsed command line; a flag the command does not know exits 2 through argparse, naming the closest known
    flags ("did you mean --fov-deg?")."""
    parser, subs = _parsers()
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        sub = subs[args.command]
        full = _parsers(fields=True)[1][args.command].format_help()  # every flag, the field flags included
        known = sorted(set(re.findall(r"(?<![\w-])--[a-z][\w-]*", full)))
        hints = [f"{u.split('=')[0]}: did you mean {', '.join(close)}?" for u in unknown if u.startswith("-")
                 and (close := difflib.get_close_matches(u.split("=")[0], known, n=3, cutoff=0.75))]
        sub.error(f"unrecognized arguments: {' '.join(unknown)}" + "".join(f"; {h}" for h in hints))
    needed = {"export": ("--out", "--num"), "preview": ("--out",)}.get(args.command, ())
    missing = [f for f in needed if getattr(args, f[2:]) is None]
    if missing and not args.print_config:  # --print-config needs neither
        subs[args.command].error(f"the following arguments are required: {', '.join(missing)}")
    return args


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status (module docstring)."""
    try:
        args = _parse(argv)
    except SystemExit as e:  # --help, --version (0) or a flag that does not parse (2); argparse printed why
        return e.code if isinstance(e.code, int) else 2
    try:
        cfg = None if args.command == "tune" else build_config(args)
        if args.command != "tune" and args.print_config:
            print(json.dumps(cfg.to_dict(), indent=2))
        elif args.command == "tune":
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
