"""The named datasets this project makes itself from the committed policies (``"generated:<name>"``) and,
for several constraints, a scripted demonstrator (:mod:`spoil_torchrl.zoo.path_follower`).

DSRL files cannot be downloaded on every machine, so the realistic experiments stand on data rolled out here,
as the paper made its Safety-Gymnasium datasets (appendix F.2). Each entry of :data:`GENERATED_DATASETS` says
which committed policies (:mod:`spoil_torchrl.zoo.policy_files`) are rolled out for how many episodes;
:func:`ensure_generated` makes the file on first use (:func:`spoil_torchrl.data.collect.collect`, atomic) and
then returns the cached copy from :func:`~spoil_torchrl.data.generated_data_dir`.

* ``point-circle1-mixed`` -- the **embedded default** of ``recipes/spoildice_dsrl.py``: 600 PointCircle1
  episodes from the four policy types, nine intermediate PPO / PPO-Lagrangian checkpoints and the random
  policy, spanning returns from about 0 to 57 and episode costs from 0 to about 250, like a DSRL dataset
  (measured: 84 s to make, 3,584 env steps/s with 8 environments in lockstep on one core).
* ``point-circle1-controlled`` -- the four typed pools of the controlled datasets (F.2), 500 episodes each, so
  that D_U can hold 2,000 trajectories; pick D_S / D_P / D_U with
  :func:`~spoil_torchrl.data.controlled_mix` on :func:`~spoil_torchrl.data.collect.segment_pools`.
* ``point-circle2-controlled`` -- the same four pools for SafetyPointCircle2-v0.
* ``point-circle2-walls`` -- PointCircle2 with each wall's own cost (``cost_x_wall``, ``cost_y_wall``): the four
  typed pools and two demonstrators each trained against one wall's cost (``x-wall-safe``, ``y-wall-safe``),
  300 episodes each, for several constraints (``docs/several_constraints.md``).
* ``point-circle2-ellipse-walls`` -- the same, with two scripted demonstrators in place of the trained ones:
  each follows an ellipse that keeps one pair of walls and crosses the other on every lap (``x-wall-ellipse``,
  ``y-wall-ellipse``; :class:`~spoil_torchrl.zoo.path_follower.EllipseFollower`).
* ``half-cheetah-velocity-controlled`` -- the same four pools for SafetyHalfCheetahVelocity-v1 (2,000 episodes
  of 1,000 steps).
* ``hopper-velocity-controlled`` -- the same four pools for SafetyHopperVelocity-v1 (2,000 episodes of at most
  1,000 steps: a hopper that falls ends its episode).
* ``walker2d-velocity-controlled`` -- the same four pools for SafetyWalker2dVelocity-v1 (2,000 episodes of at
  most 1,000 steps).
* ``ant-velocity-controlled`` -- the same four pools for SafetyAntVelocity-v1 (2,000 episodes of at most 1,000
  steps).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

from spoil_torchrl.data.collect import RANDOM_POLICY, Segment, collect
from spoil_torchrl.data.labeling import POOLS
from spoil_torchrl.files import code_digest
from spoil_torchrl.stack import current_stack, stack_differences, stack_label
from spoil_torchrl.tasks import UnknownDatasetError


@dataclass(frozen=True)
class GeneratedDataset:
    """A dataset recipe: ``segments`` of ``env_id`` rolled out with ``seed``."""

    name: str
    env_id: str
    segments: tuple[Segment, ...]
    description: str
    seed: int = 0
    #: record each constraint's own cost too (``cost_<name>`` arrays: :mod:`spoil_torchrl.envs.cost_components`)
    components: bool = False

    @property
    def episodes(self) -> int:
        return sum(s.episodes for s in self.segments)

    def fingerprint(self, num_envs: int) -> str:
        """A hash of everything that determines the file's content: the recipe, ``num_envs``, the bytes of
        every committed policy it rolls out (a policy re-exported under the same name makes the file again) and,
        where it rolls out a scripted ellipse follower, the code of :mod:`spoil_torchrl.zoo.path_follower`
        (the follower's code changed makes the file again; an edit of its docstrings or comments does not)."""
        from spoil_torchrl.zoo import path_follower
        from spoil_torchrl.zoo.policy_files import zoo_policy

        policies = sorted({s.policy for s in self.segments if s.policy.startswith("zoo:")})
        digests = [hashlib.sha256(zoo_policy(self.env_id, p[4:]).read_bytes()).hexdigest() for p in policies]
        if any(s.policy.startswith(path_follower.ELLIPSE_PREFIX) for s in self.segments):
            digests.append(code_digest(path_follower.__file__))
        recipe = [self.env_id, self.seed, num_envs, [asdict(s) for s in self.segments], digests]
        text = json.dumps(recipe + (["components"] if self.components else []))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _typed(episodes: int) -> tuple[Segment, ...]:
    return tuple(Segment(pool, f"zoo:{pool}", episodes) for pool in POOLS)


GENERATED_DATASETS: dict[str, GeneratedDataset] = {
    d.name: d
    for d in [
        GeneratedDataset(
            "point-circle1-mixed",
            "SafetyPointCircle1-v0",
            _typed(60)
            + tuple(
                Segment(name, f"zoo:{name}", 35)
                for name in (
                    "ppolag-0100k",
                    "ppolag-0200k",
                    "ppolag-0300k",
                    "ppolag-0500k",
                    "ppolag-0750k",
                    "ppolag-0800k",
                    "ppo-0050k",
                    "ppo-0100k",
                    "ppo-0250k",
                )
            )
            + (Segment("random", RANDOM_POLICY, 45),),
            "DSRL-style mixed PointCircle1 data (the main recipe's embedded default)",
        ),
        GeneratedDataset(
            "point-circle1-controlled",
            "SafetyPointCircle1-v0",
            _typed(500),
            "controlled PointCircle1 pools: 500 episodes of each policy type (paper F.2)",
        ),
        GeneratedDataset(
            "point-circle2-controlled",
            "SafetyPointCircle2-v0",
            _typed(500),
            "controlled PointCircle2 pools: 500 episodes of each policy type (paper F.2)",
        ),
        GeneratedDataset(
            "point-circle2-walls",
            "SafetyPointCircle2-v0",
            _typed(300) + tuple(Segment(wall, f"zoo:{wall}", 300) for wall in ("x-wall-safe", "y-wall-safe")),
            "PointCircle2 pools with each wall's own cost: the four policy types and two demonstrators trained "
            "against one wall's cost (x-wall-safe, y-wall-safe), 300 episodes each",
            components=True,
        ),
        GeneratedDataset(
            "point-circle2-ellipse-walls",
            "SafetyPointCircle2-v0",
            _typed(300)
            + (
                Segment("x-wall-ellipse", "ellipse:0.9,1.6", 300),
                Segment("y-wall-ellipse", "ellipse:1.6,0.9", 300),
            ),
            "PointCircle2 pools with each wall's own cost: the four policy types and two scripted demonstrators "
            "that keep one pair of walls and cross the other on every lap (ellipses with half-axes 0.9 and 1.6), "
            "300 episodes each",
            components=True,
        ),
        GeneratedDataset(
            "half-cheetah-velocity-controlled",
            "SafetyHalfCheetahVelocity-v1",
            _typed(500),
            "controlled HalfCheetahVelocity pools: 500 episodes of each policy type (paper F.2)",
        ),
        GeneratedDataset(
            "hopper-velocity-controlled",
            "SafetyHopperVelocity-v1",
            _typed(500),
            "controlled HopperVelocity pools: 500 episodes of each policy type (paper F.2)",
        ),
        GeneratedDataset(
            "walker2d-velocity-controlled",
            "SafetyWalker2dVelocity-v1",
            _typed(500),
            "controlled Walker2dVelocity pools: 500 episodes of each policy type (paper F.2)",
        ),
        GeneratedDataset(
            "ant-velocity-controlled",
            "SafetyAntVelocity-v1",
            _typed(500),
            "controlled AntVelocity pools: 500 episodes of each policy type (paper F.2)",
        ),
    ]
}

#: The main recipe's default dataset.
DEFAULT_DATASET = "point-circle1-mixed"


def get_generated(name: str) -> GeneratedDataset:
    """The recipe of a named generated dataset; an unknown name raises with the known ones.

    Examples:
        >>> spec = get_generated("point-circle1-controlled")
        >>> spec.env_id, spec.episodes, [segment.label for segment in spec.segments]
        ('SafetyPointCircle1-v0', 2000, ['safe-high', 'safe-medium', 'unsafe-high', 'unsafe-medium'])
        >>> spec.segments[0]
        Segment(label='safe-high', policy='zoo:safe-high', episodes=500)
        >>> get_generated("point-circle3")
        Traceback (most recent call last):
        ...
        spoil_torchrl.tasks.UnknownDatasetError: unknown generated dataset 'point-circle3'; known: ...
    """
    if name not in GENERATED_DATASETS:
        raise UnknownDatasetError(
            f"unknown generated dataset {name!r}; known: {', '.join(GENERATED_DATASETS)}"
        )
    return GENERATED_DATASETS[name]


def generated_data_dir() -> Path:
    """``$SPOIL_TORCHRL_DATA_DIR`` if set, else ``~/.cache/spoil_torchrl/generated``.

    Examples:
        >>> from unittest import mock
        >>> with mock.patch.dict(os.environ, {"SPOIL_TORCHRL_DATA_DIR": "/data/generated"}):
        ...     generated_data_dir()
        PosixPath('/data/generated')
        >>> with mock.patch.dict(os.environ):
        ...     _ = os.environ.pop("SPOIL_TORCHRL_DATA_DIR", None)
        ...     generated_data_dir() == Path.home() / ".cache" / "spoil_torchrl" / "generated"
        True
    """
    default = Path.home() / ".cache" / "spoil_torchrl" / "generated"
    return Path(os.environ.get("SPOIL_TORCHRL_DATA_DIR", default)).expanduser()


def generated_path(name: str) -> Path:
    """Where the dataset ``name`` is cached (it may not exist yet).

    Examples:
        >>> from unittest import mock
        >>> with mock.patch.dict(os.environ, {"SPOIL_TORCHRL_DATA_DIR": "/data/generated"}):
        ...     generated_path(DEFAULT_DATASET)
        PosixPath('/data/generated/point-circle1-mixed.hdf5')
    """
    return generated_data_dir() / f"{name}.hdf5"


def missing_generated_error(name: str) -> str:
    """What to do about a generated dataset ``name`` that is not in :func:`generated_data_dir`."""
    if name in GENERATED_DATASETS:
        how = f"make it with `python recipes/collect_demos.py name={name}`"
    else:
        how = (
            f"it is not one of the known generated datasets ({', '.join(GENERATED_DATASETS)}); add it to "
            "spoil_torchrl/data/generated.py and make it with recipes/collect_demos.py"
        )
    return (
        f"generated dataset {name!r} not found at {generated_path(name)}; {how} "
        "(or set SPOIL_TORCHRL_DATA_DIR to where it lives)"
    )


#: A temporary file of a dataset write that has not changed for this long belongs to a write that was killed.
STALE_SECONDS = 3600.0


def report_stale_temporaries(path: Path) -> list[Path]:
    """Warn about ``<name>.hdf5.<random>.tmp`` files beside ``path`` that no write has touched for
    :data:`STALE_SECONDS` (left by a write that was killed: a live write keeps its file growing) and say how
    to remove them; returns them. They are not deleted: a write on another machine sharing the folder could
    still be slow.

    Examples:
        >>> import os, tempfile, time
        >>> folder = Path(tempfile.mkdtemp())
        >>> old = folder / "data.hdf5.x1y2.tmp"; _ = old.write_bytes(b"")
        >>> os.utime(old, (time.time() - 7200, time.time() - 7200))
        >>> import warnings
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     stale = report_stale_temporaries(folder / "data.hdf5")
        >>> [p.name for p in stale], "interrupted writes" in str(caught[0].message)
        (['data.hdf5.x1y2.tmp'], True)
    """
    now = time.time()
    try:
        candidates = list(path.parent.glob(f"{path.name}.*.tmp"))
    except OSError:
        return []
    stale = []
    for tmp in sorted(candidates):
        try:
            if now - tmp.stat().st_mtime > STALE_SECONDS:
                stale.append(tmp)
        except OSError:  # removed meanwhile
            continue
    if stale:
        size = sum(p.stat().st_size for p in stale if p.exists()) / 2**20
        warnings.warn(
            f"{len(stale)} temporary file(s) of interrupted writes of {path.name} ({size:.0f} MB), untouched for "
            f"over {STALE_SECONDS / 3600:.0f} h: {', '.join(p.name for p in stale)} in {path.parent}; delete them "
            f"(rm {path.parent}/{path.name}.*.tmp) once no other machine is writing this dataset",
            stacklevel=2,
        )
    return stale


def ensure_generated(name: str, *, force: bool = False, num_envs: int = 8, progress: bool = True) -> Path:
    """The path of the generated dataset ``name``, making it first if it is not cached (or ``force``).

    Making it rolls out the committed policies (needs the ``safety`` extra); the file appears only once it is
    complete. A cached file made from a different recipe (another segment list, seed or ``num_envs``: its
    metadata's ``fingerprint`` differs) or on another software stack (its ``stack``:
    :func:`spoil_torchrl.stack.stack_differences`; the physics differ between MuJoCo releases) is made again,
    with a line that says why. Two processes making the same dataset at once both
    work, and the last one to finish leaves its (identical) file. Examples are in ``recipes/collect_demos.py``
    and the tests.
    """
    from spoil_torchrl.data.hdf5 import read_metadata

    spec = get_generated(name)
    path = generated_path(name)
    report_stale_temporaries(path)
    fingerprint = spec.fingerprint(num_envs)
    if path.exists() and not force:
        cached = read_metadata(path)
        other_stack = stack_differences(cached.get("stack"))
        if cached.get("fingerprint") == fingerprint and not other_stack:
            return path
        if cached.get("fingerprint") != fingerprint:
            print(
                f"{path}: made by another recipe (fingerprint {cached.get('fingerprint')}, now {fingerprint}: the "
                "segments, seed, num_envs, the bytes of a policy it rolls out or the ellipse follower's code "
                "changed); making it again"
            )
        elif cached.get("stack") is None:
            print(
                f"{path}: made before datasets recorded their software stack; making it again for this stack"
            )
        else:
            print(
                f"{path}: made on another software stack ({stack_label(cached.get('stack'))}; here "
                f"{stack_label(current_stack())}: {', '.join(other_stack)}), whose simulator gives other "
                "episodes; making it again for this stack"
            )
    return collect(
        spec.env_id,
        spec.segments,
        path,
        seed=spec.seed,
        num_envs=num_envs,
        progress=progress,
        metadata={"name": spec.name, "description": spec.description, "fingerprint": fingerprint},
        components=spec.components,
    )
