"""The command line explains itself: help from the config docstrings, parse errors that name the flag,
documented exit codes, a closing summary, and no Warp noise."""

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import flowsynth as fs
from flowsynth import cli
from flowsynth.cli import main

REPO = Path(__file__).resolve().parents[1]


def _source_docstrings() -> dict[str, str]:
    """Field docstrings read with a regex over config.py (independent of flowsynth._flags' ast reader)."""
    src = (REPO / "flowsynth" / "scene" / "config.py").read_text()
    body = src[src.index("class BouncingThingsConfig"):src.index("def __post_init__")]
    pat = re.compile(r'^    (\w+): [^\n=]+= .*?\n    """(.*?)"""', re.S | re.M)
    return {m.group(1): " ".join(m.group(2).split()) for m in pat.finditer(body)}


def test_export_help_fields_lists_every_flag_with_type_default_and_meaning(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "2000")  # one line per flag, no wrapping inside words
    assert main(["export", "--help-fields"]) == 0
    lines = capsys.readouterr().out.splitlines()
    docs = _source_docstrings()
    fields = dataclasses.fields(fs.BouncingThingsConfig)
    assert len(docs) == len(fields)
    for f in fields:
        flag = "--" + f.name.replace("_", "-")
        k = next(i for i, line in enumerate(lines) if line.startswith(f"  {flag} "))
        entry = lines[k] + (" " + lines[k + 1].strip() if not lines[k + 1].strip().startswith("-") else "")
        default = f.default
        shown = ("none" if default is None else ",".join(map(str, default)) if isinstance(default, tuple)
                 else str(default))
        assert entry.endswith(f"[{str(f.type).replace(' ', '')}, default {shown}]"), entry
        assert docs[f.name].replace("``", "") in entry, (flag, entry)
    parser = cli._parser(fields=True)
    export = next(a for a in parser._actions if a.dest == "command").choices["export"]
    for action in export._actions:  # every other flag says what it means and its default
        if action.dest not in ("help", "help_fields"):
            assert action.help and ("default" in action.help or "required" in action.help), action.dest


@pytest.mark.parametrize("flag,value,form", [
    ("--fov-deg", "abc", "expected a number, such as 60.0"),
    ("--width", "1.5", "expected an integer, such as 320"),
    ("--num-objects", "3", "expected 2 integers separated by commas, such as 4,12"),
    ("--room-size", "1,2", "expected 3 numbers separated by commas, such as 10.0,8.0,6.0"),
    ("--substeps", "many", "expected an integer or none"),
    ("--num", "x", "expected an integer"),
])
def test_parse_errors_name_the_flag_and_the_form(tmp_path, capsys, flag, value, form, small_flags):
    args = ["export", "--out", str(tmp_path / "o"), "--num", "1", *small_flags, flag, value]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: {form}" in err and repr(value) in err, err
    assert not (tmp_path / "o").exists()


def test_config_value_errors_name_the_flag(tmp_path, capsys):
    assert main(["export", "--out", str(tmp_path / "o"), "--num", "1", "--width", "-3"]) == 2
    assert "--width: width must be an integer >= 1" in capsys.readouterr().err


def test_exit_codes_documented_in_docstring_help_and_readme(capsys):
    codes = re.findall(r"^  (\d+) ", cli.__doc__.split("Exit status:")[1], re.M)
    assert codes == ["0", "1", "2", "3", "130"]
    assert main(["--help"]) == 0
    help_text = capsys.readouterr().out
    readme = (REPO / "README.md").read_text()
    readme_codes = readme[readme.index("Exit status"):]
    for code in codes:
        assert re.search(rf"^  {code} ", help_text, re.M), code
        assert re.search(rf"\b{code}\b", readme_codes[:1200]), code


def test_closing_summary_is_singular_and_says_how_to_load(tmp_path, capsys, small_flags):
    """The closing line says what the run did: a first run wrote its sample, a re-run found it and wrote nothing, a
    re-run after a file was deleted wrote it again as a repair; and how to load the export."""
    argv = ["export", "--out", str(tmp_path / "one"), "--num", "1", "--no-progress", "--outputs", "depth",
            *small_flags]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "holds 1 sample: 0 present (whole), 1 written (0 of them repaired)" in out and "1 samples" not in out
    assert "layout native" in out and re.search(r" in \d+\.\d s", out)
    assert main(argv) == 0
    assert "holds 1 sample: 1 present (whole), 0 written (0 of them repaired)" in capsys.readouterr().out
    (tmp_path / "one" / "00000" / "depth_0000.exr").unlink()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "holds 1 sample: 0 present (whole), 1 written (1 of them repaired)" in out
    hint = out.split("load it in Python with ")[1].strip()
    ds = eval(hint, {"flowsynth": fs})
    assert len(ds) == 1 and ds.root == tmp_path / "one"


def test_no_warp_driver_notice_on_stderr(tmp_path):
    """A CPU-only machine has no CUDA driver; Warp's C library says so on stderr, which flowsynth drops."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, "-c", "from flowsynth.kernels import wp_runtime; wp_runtime()"],
                       capture_output=True, text=True, cwd=tmp_path, env=env)
    assert r.returncode == 0 and "CUDA driver" not in r.stderr, r.stderr


def test_warp_init_filter_keeps_other_lines(capfd):
    """The filter drops exactly the no-driver line, written by C code to file descriptor 2."""
    from flowsynth.kernels import _init_without_driver_notice

    class FakeWarp:
        @staticmethod
        def init():
            os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution ...\n")
            os.write(2, b"something the user must see\n")

    _init_without_driver_notice(FakeWarp)
    err = capfd.readouterr().err
    assert err == "something the user must see\n"


def _png_config(path: Path) -> dict:
    from PIL import Image

    return json.loads(Image.open(path).text["flowsynth:config"])


def test_readme_preview_shows_the_current_defaults():
    """docs/preview.png was made by scripts/make_preview.py from today's default config (not a stale one)."""
    assert _png_config(REPO / "docs" / "preview.png") == json.loads(json.dumps(fs.BouncingThingsConfig().to_dict()))


def test_preview_script_writes_the_config_it_used(tmp_path, small_flags, small_config):
    out = tmp_path / "p.png"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "make_preview.py"), "--out", str(out), *small_flags],
                       capture_output=True, text=True, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr
    cfg = small_config  # what small_flags say
    assert _png_config(out) == json.loads(json.dumps(cfg.to_dict()))


def test_interrupt_exits_130_with_a_resume_hint(tmp_path, capsys, monkeypatch, small_flags):
    import flowsynth.export

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(flowsynth.export, "export_dataset", interrupted)
    assert main(["export", "--out", str(tmp_path / "o"), "--num", "1", *small_flags]) == 130
    assert "re-run the same command to resume" in capsys.readouterr().err


def test_flag_types_cover_bool_fields():
    """A future bool config field parses true/false forms and refuses others, naming the form."""
    import argparse

    from flowsynth._flags import flag_type

    @dataclasses.dataclass
    class WithBool:
        mirror: bool = False

    parse = flag_type(dataclasses.fields(WithBool)[0])
    assert [parse(x) for x in ("true", "Yes", "1", "off", "0", "false")] == [True, True, True, False, False, False]
    with pytest.raises(argparse.ArgumentTypeError, match="expected true or false"):
        parse("maybe")
