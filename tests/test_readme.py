"""The README's code blocks run."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_loop_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    loop = [b for b in blocks if "SpoilDICELoss(" in b]
    assert loop, "the README lost its training-loop example"
    namespace: dict = {}
    exec(compile(loop[0], "README.md", "exec"), namespace)
    assert "lagrange" in capsys.readouterr().out
    trainer = [b for b in blocks if "offline_trainer(" in b]
    assert trainer, "the README lost its Trainer example"
    exec(compile(trainer[0], "README.md", "exec"), namespace)
    assert "steps done: 20" in capsys.readouterr().out
    diagnostics = [b for b in blocks if "dice_diagnostics(" in b]
    assert diagnostics, "the README lost its diagnostics example"
    exec(compile(diagnostics[0], "README.md", "exec"), namespace)
    assert "of the weight mass sits on transitions with true cost > 0" in capsys.readouterr().out
