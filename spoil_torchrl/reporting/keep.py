"""The finished runs of a sweep kept apart: each one's ``results.json`` and ``config.yaml``, all that the reports
read (``spoil-report``, ``--figure``), without checkpoints, logs or rollouts, to commit or share while the sweep
goes on (``spoil-report --keep``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from spoil_torchrl.files import write_atomic
from spoil_torchrl.reporting.experiments import finished_results

#: What :func:`keep_finished` copies of a finished run: what its tables and figures read, nothing else.
KEPT_FILES = ("config.yaml", "results.json")


@dataclass
class Kept:
    """What :func:`keep_finished` did: run folders (relative to ``dest``) copied now, found already kept the
    same, and refused because other files are kept there (or another run of this call went there first);
    ``skipped`` lists as ``(results.json, reason)`` the runs that did not finish or have no ``config.yaml``."""

    copied: list[str] = field(default_factory=list)
    already: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    skipped: list[tuple[Path, str]] = field(default_factory=list)


def _overlap(a: Path, b: Path) -> bool:
    return a.is_relative_to(b) or b.is_relative_to(a)


def keep_finished(folders: Sequence[str | Path], dest: str | Path) -> Kept:
    """Copy the ``results.json`` and ``config.yaml`` of every finished run under ``folders`` into ``dest``, each
    at its path relative to the folder it was found in. A run still training, killed or failed is skipped, as is
    one without a ``config.yaml`` (a report could not check its training budget); one kept before with the same
    files is left as it is; one kept before with other contents (a run started over, a file edited) is refused,
    never overwritten, as is a second run that would land where this call already put one. Each file is
    written atomically, ``results.json`` last, so a copy cut short is finished by the next call.

    Raises:
        FileNotFoundError: a folder does not exist (before anything is copied).
        ValueError: two of ``folders`` and ``dest`` overlap (one inside the other), before anything is copied.

    Examples:
        >>> import json, tempfile
        >>> runs, kept = Path(tempfile.mkdtemp()), Path(tempfile.mkdtemp()) / "kept"
        >>> cell = runs / "fig4b" / "bc" / "seed0"
        >>> cell.mkdir(parents=True)
        >>> _ = (cell / "config.yaml").write_text("seed: 0\\n")
        >>> _ = (cell / "results.json").write_text(json.dumps({"status": "finished"}))
        >>> keep_finished([runs], kept).copied
        ['fig4b/bc/seed0']
        >>> keep_finished([runs], kept).already
        ['fig4b/bc/seed0']
    """
    dest, folders = Path(dest), [Path(folder) for folder in folders]
    for folder in folders:
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: no such folder")
    places = [(str(dest), dest.resolve()), *((str(f), f.resolve()) for f in folders)]
    for i, (name, place) in enumerate(places):
        for other, other_place in places[i + 1 :]:
            if _overlap(place, other_place):
                raise ValueError(
                    f"{name} and {other} overlap (one inside the other): give folders apart from each other "
                    "and from where the runs are kept"
                )
    kept, written = Kept(), set()
    for folder in folders:
        for path, _ in finished_results([folder], kept.skipped):
            relative = str(path.parent.relative_to(folder))
            if not (path.parent / "config.yaml").is_file():
                kept.skipped.append((path, "no config.yaml (a report could not check its training budget)"))
                continue
            contents = {name: (path.parent / name).read_bytes() for name in KEPT_FILES}
            target = dest / relative
            if relative in written:
                kept.refused.append(relative)
            elif (target / "results.json").is_file():
                same = all(
                    (target / name).is_file() and (target / name).read_bytes() == data
                    for name, data in contents.items()
                )
                (kept.already if same else kept.refused).append(relative)
            else:
                for name in KEPT_FILES:  # results.json last: it marks the copy whole
                    write_atomic(target / name, contents[name])
                kept.copied.append(relative)
            written.add(relative)
    return kept
