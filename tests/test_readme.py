"""The README's code blocks run, with the three of docs/usage.md that continue its loop example."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README, USAGE = ROOT / "README.md", ROOT / "docs" / "usage.md"


def test_readme_loop_example_runs(capsys):
    text = README.read_text() + USAGE.read_text()  # the loop example first, then what continues it
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    loop = [b for b in blocks if "SpoilDICELoss(" in b]
    assert loop, "the README lost its training-loop example"
    namespace: dict = {}
    exec(compile(loop[0], "README.md", "exec"), namespace)
    assert "lagrange" in capsys.readouterr().out
    trainer = [b for b in blocks if "offline_trainer(" in b]
    assert trainer, "docs/usage.md lost its Trainer example"
    exec(compile(trainer[0], "README.md", "exec"), namespace)
    assert "steps done: 20" in capsys.readouterr().out
    diagnostics = [b for b in blocks if "dice_diagnostics(" in b]
    assert diagnostics, "docs/usage.md lost its diagnostics example"
    exec(compile(diagnostics[0], "README.md", "exec"), namespace)
    assert "of the weight mass sits on transitions with true cost > 0" in capsys.readouterr().out
    constraints = [b for b in blocks if "constraints=2" in b]
    assert constraints, "docs/usage.md lost its several-constraints example"
    exec(compile(constraints[0], "README.md", "exec"), namespace)
    printed = capsys.readouterr().out
    assert "lagrange_1" in printed and "support_fraction_1" in printed
