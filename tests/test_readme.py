"""Every ```python block of README.md runs as written, in order, in one namespace (as a reader pastes them)."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_blocks_run(tmp_path, monkeypatch, capsys):
    blocks = re.findall(r"^```python\n(.*?)^```", README.read_text(), re.S | re.M)
    assert len(blocks) >= 3
    monkeypatch.chdir(tmp_path)  # the blocks write relative paths such as out/...
    namespace: dict = {"__name__": "__readme__"}
    for k, code in enumerate(blocks):
        exec(compile(code, f"README.md python block {k + 1}", "exec"), namespace)
    out = capsys.readouterr().out.splitlines()
    # the printed values are the ones the README's comments state
    assert out[0] == "torch.Size([2, 2, 3, 192, 256]) torch.Size([2, 1, 2, 192, 256])"
    assert out[1] == "['depth', 'flow_fw', 'index', 'occ_fw', 'rgb', 'seed']"  # a sample holds what was asked
    assert out[2] == "torch.Size([3, 3]) 2"  # and the metadata when asked for ("meta")
    assert out[3] == "default 0"  # the Mixture block: index 12345 drawn from default, index 3 from chairs
    assert out[4] == "torch.Size([1, 2, 96, 128]) torch.bool"  # the 2D layers block: one pair, its occlusion
    assert out[5] == "['things', 'layers']"  # the mixture of both kinds, back from its preset file
    assert float(out[6].split("(")[1].split(")")[0]) == 3.5
    assert out[-3] == "2 torch.Size([1, 2, 192, 256])"
    assert out[-2] == "(2, 1, 2, 96, 128) True"  # a device batch's sample 1 is the stream's sample 1
    assert out[-1] == str([list(range(8)), list(range(8, 16))])  # the DDP block, one process: each epoch whole
