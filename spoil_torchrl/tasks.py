"""Task registry: the 38 DSRL datasets and the paper's IL-SP thresholds.

Per-dataset constants (file name, episode length, R_max / R_min used for return normalisation, max episode cost,
trajectory count) are those of DSRL's ``dsrl/infos.py`` (liuzuxin/DSRL, commit 6cb1763); observation / action
sizes and the IL-SP cost and return thresholds are the paper's Table C, for the 21 tasks it used. Where no
reliable source gives the sizes they are ``None`` and a loaded file's sizes are taken as they are.
Nothing in the library hard-codes a task: look it up here.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

#: Where DSRL hosts its files since Nov 2025 (the DSRL repository's README); ``<file>`` is appended.
DSRL_BASE_URL = "https://huggingface.co/datasets/YYY-45/DSRL/resolve/main/"


@dataclass(frozen=True)
class DSRLDataset:
    """One DSRL dataset and the constants needed to use it.

    Attributes:
        dataset_id: gym id of the offline environment, e.g. ``"OfflinePointCircle1Gymnasium-v0"``.
        file_name: the HDF5 file name, ``<EnvName>-<max cost>-<n traj>.hdf5``.
        episode_length: maximum episode length T.
        max_return, min_return: DSRL's normalisation constants, normalised return = (R - min) / (max - min).
        max_cost: largest episode cost in the dataset.
        n_trajectories: number of trajectories in the file.
        observation_dim, action_dim: sizes, or ``None`` where unknown.
        cost_threshold, return_threshold: the paper's Table C values (``None`` for tasks it did not use).
        paper_name: the task's name in the paper's tables, if it used it.
    """

    dataset_id: str
    file_name: str
    episode_length: int
    max_return: float
    min_return: float
    max_cost: float
    observation_dim: int | None = None
    action_dim: int | None = None
    cost_threshold: float | None = None
    return_threshold: float | None = None
    paper_name: str | None = None

    @property
    def n_trajectories(self) -> int:
        return int(self.file_name.rsplit("-", 1)[1].split(".")[0])

    @property
    def url(self) -> str:
        return DSRL_BASE_URL + self.file_name


_DATASETS = [
    # Bullet-Safety-Gym
    DSRLDataset(
        dataset_id="OfflineAntCircle-v0",
        file_name="SafetyAntCircle-v0-200-5728.hdf5",
        episode_length=500,
        max_return=460.7091979980469,
        min_return=0.0177031010389328,
        max_cost=200.0,
        observation_dim=33,
        action_dim=8,
        cost_threshold=40,
        return_threshold=225.71,
        paper_name="AntCircle",
    ),
    DSRLDataset(
        dataset_id="OfflineAntRun-v0",
        file_name="SafetyAntRun-v0-150-1816.hdf5",
        episode_length=200,
        max_return=955.4818725585938,
        min_return=0.001767391717990563,
        max_cost=150.0,
        observation_dim=34,
        action_dim=8,
        cost_threshold=40,
        return_threshold=664.83,
        paper_name="AntRun",
    ),
    DSRLDataset(
        dataset_id="OfflineBallCircle-v0",
        file_name="SafetyBallCircle-v0-80-886.hdf5",
        episode_length=200,
        max_return=881.46337890625,
        min_return=0.38312244415283203,
        max_cost=80.0,
        observation_dim=7,
        action_dim=2,
        cost_threshold=40,
        return_threshold=712.45,
        paper_name="BallCircle",
    ),
    DSRLDataset(
        dataset_id="OfflineBallRun-v0",
        file_name="SafetyBallRun-v0-80-940.hdf5",
        episode_length=100,
        max_return=1327.445556640625,
        min_return=26.339754104614258,
        max_cost=80.0,
        observation_dim=8,
        action_dim=2,
        cost_threshold=40,
        return_threshold=556.19,
        paper_name="BallRun",
    ),
    # CarCircle: the paper's Table C says 7 observation dims, DSRL's infos.py says 8; unverified, so not checked.
    DSRLDataset(
        dataset_id="OfflineCarCircle-v0",
        file_name="SafetyCarCircle-v0-100-1450.hdf5",
        episode_length=300,
        max_return=534.3060913085938,
        min_return=3.484419822692871,
        max_cost=100.0,
        action_dim=2,
        cost_threshold=40,
        return_threshold=435.21,
        paper_name="CarCircle",
    ),
    DSRLDataset(
        dataset_id="OfflineCarRun-v0",
        file_name="SafetyCarRun-v0-40-651.hdf5",
        episode_length=200,
        max_return=574.6533203125,
        min_return=204.28726196289062,
        max_cost=40.0,
        observation_dim=8,
        action_dim=2,
        cost_threshold=20,
        return_threshold=566.21,
        paper_name="CarRun",
    ),
    DSRLDataset(
        dataset_id="OfflineDroneCircle-v0",
        file_name="SafetyDroneCircle-v0-100-1923.hdf5",
        episode_length=300,
        max_return=996.38916015625,
        min_return=207.794189453125,
        max_cost=100.0,
        observation_dim=17,
        action_dim=4,
        cost_threshold=40,
        return_threshold=713.46,
        paper_name="DroneCircle",
    ),
    DSRLDataset(
        dataset_id="OfflineDroneRun-v0",
        file_name="SafetyDroneRun-v0-140-1990.hdf5",
        episode_length=200,
        max_return=682.8330078125,
        min_return=10.557029724121094,
        max_cost=140.0,
        observation_dim=18,
        action_dim=4,
        cost_threshold=40,
        return_threshold=411.47,
        paper_name="DroneRun",
    ),
    # Safety-Gymnasium navigation
    DSRLDataset(
        dataset_id="OfflineCarButton1Gymnasium-v0",
        file_name="SafetyCarButton1Gymnasium-v0-250-2656.hdf5",
        episode_length=1000,
        max_return=44.420003345738984,
        min_return=0.0028926206826067613,
        max_cost=250.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarButton2Gymnasium-v0",
        file_name="SafetyCarButton2Gymnasium-v0-300-3755.hdf5",
        episode_length=1000,
        max_return=41.99513815522894,
        min_return=0.001767391717990563,
        max_cost=300.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarCircle1Gymnasium-v0",
        file_name="SafetyCarCircle1Gymnasium-v0-250-1271.hdf5",
        episode_length=500,
        max_return=24.94155502319336,
        min_return=8.037073135375977,
        max_cost=250.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarCircle2Gymnasium-v0",
        file_name="SafetyCarCircle2Gymnasium-v0-400-940.hdf5",
        episode_length=500,
        max_return=25.950098037719727,
        min_return=5.113386154174805,
        max_cost=398.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarGoal1Gymnasium-v0",
        file_name="SafetyCarGoal1Gymnasium-v0-120-1671.hdf5",
        episode_length=1000,
        max_return=39.907809198384705,
        min_return=0.012232819540852091,
        max_cost=120.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarGoal2Gymnasium-v0",
        file_name="SafetyCarGoal2Gymnasium-v0-200-4105.hdf5",
        episode_length=1000,
        max_return=28.902897990056502,
        min_return=0.001032874531954775,
        max_cost=200.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarPush1Gymnasium-v0",
        file_name="SafetyCarPush1Gymnasium-v0-200-2871.hdf5",
        episode_length=1000,
        max_return=16.304467598905237,
        min_return=0.013700173533941762,
        max_cost=200.0,
    ),
    DSRLDataset(
        dataset_id="OfflineCarPush2Gymnasium-v0",
        file_name="SafetyCarPush2Gymnasium-v0-250-4407.hdf5",
        episode_length=1000,
        max_return=15.141648491514314,
        min_return=0.00029391133526335267,
        max_cost=250.0,
    ),
    DSRLDataset(
        dataset_id="OfflinePointButton1Gymnasium-v0",
        file_name="SafetyPointButton1Gymnasium-v0-200-2268.hdf5",
        episode_length=1000,
        max_return=41.19301568767707,
        min_return=0.008822109034937853,
        max_cost=200.0,
        observation_dim=76,
        action_dim=2,
        cost_threshold=40,
        return_threshold=27.12,
        paper_name="PointButton1",
    ),
    DSRLDataset(
        dataset_id="OfflinePointButton2Gymnasium-v0",
        file_name="SafetyPointButton2Gymnasium-v0-250-3288.hdf5",
        episode_length=1000,
        max_return=42.8985953616709,
        min_return=0.014114166087574098,
        max_cost=250.0,
        observation_dim=76,
        action_dim=2,
        cost_threshold=80,
        return_threshold=29.75,
        paper_name="PointButton2",
    ),
    DSRLDataset(
        dataset_id="OfflinePointCircle1Gymnasium-v0",
        file_name="SafetyPointCircle1Gymnasium-v0-200-1098.hdf5",
        episode_length=500,
        max_return=61.72819519042969,
        min_return=20.067626953125,
        max_cost=200.0,
        observation_dim=28,
        action_dim=2,
        cost_threshold=40,
        return_threshold=44.85,
        paper_name="PointCircle1",
    ),
    DSRLDataset(
        dataset_id="OfflinePointCircle2Gymnasium-v0",
        file_name="SafetyPointCircle2Gymnasium-v0-300-895.hdf5",
        episode_length=500,
        max_return=54.02184295654297,
        min_return=20.478347778320312,
        max_cost=299.0,
        observation_dim=28,
        action_dim=2,
        cost_threshold=80,
        return_threshold=43.1,
        paper_name="PointCircle2",
    ),
    DSRLDataset(
        dataset_id="OfflinePointGoal1Gymnasium-v0",
        file_name="SafetyPointGoal1Gymnasium-v0-100-2022.hdf5",
        episode_length=1000,
        max_return=30.071114857340543,
        min_return=0.01196012764197707,
        max_cost=100.0,
        observation_dim=60,
        action_dim=2,
        cost_threshold=40,
        return_threshold=21.67,
        paper_name="PointGoal1",
    ),
    DSRLDataset(
        dataset_id="OfflinePointGoal2Gymnasium-v0",
        file_name="SafetyPointGoal2Gymnasium-v0-200-3442.hdf5",
        episode_length=1000,
        max_return=27.717709787852737,
        min_return=0.002616959830266108,
        max_cost=200.0,
        observation_dim=60,
        action_dim=2,
        cost_threshold=80,
        return_threshold=20.4,
        paper_name="PointGoal2",
    ),
    DSRLDataset(
        dataset_id="OfflinePointPush1Gymnasium-v0",
        file_name="SafetyPointPush1Gymnasium-v0-150-2379.hdf5",
        episode_length=1000,
        max_return=16.518654299293367,
        min_return=0.0014001545292344209,
        max_cost=150.0,
    ),
    DSRLDataset(
        dataset_id="OfflinePointPush2Gymnasium-v0",
        file_name="SafetyPointPush2Gymnasium-v0-200-3242.hdf5",
        episode_length=1000,
        max_return=14.691039145644403,
        min_return=0.0012438183001730607,
        max_cost=200.0,
    ),
    # Safety-Gymnasium velocity
    DSRLDataset(
        dataset_id="OfflineAntVelocityGymnasium-v1",
        file_name="SafetyAntVelocityGymnasium-v1-250-2249.hdf5",
        episode_length=1000,
        max_return=2976.276611328125,
        min_return=6.1519012451171875,
        max_cost=250.0,
        observation_dim=27,
        action_dim=8,
        cost_threshold=40,
        return_threshold=2743.78,
        paper_name="AntVelocity",
    ),
    DSRLDataset(
        dataset_id="OfflineHalfCheetahVelocityGymnasium-v1",
        file_name="SafetyHalfCheetahVelocityGymnasium-v1-250-2495.hdf5",
        episode_length=1000,
        max_return=2806.93310546875,
        min_return=5.7509765625,
        max_cost=250.0,
        observation_dim=17,
        action_dim=6,
        cost_threshold=40,
        return_threshold=2563.55,
        paper_name="HalfCheetahVelocity",
    ),
    DSRLDataset(
        dataset_id="OfflineHopperVelocityGymnasium-v1",
        file_name="SafetyHopperVelocityGymnasium-v1-250-2240.hdf5",
        episode_length=1000,
        max_return=1911.396728515625,
        min_return=37.05154800415039,
        max_cost=250.0,
        observation_dim=11,
        action_dim=3,
        cost_threshold=40,
        return_threshold=1607.84,
        paper_name="HopperVelocity",
    ),
    DSRLDataset(
        dataset_id="OfflineSwimmerVelocityGymnasium-v1",
        file_name="SafetySwimmerVelocityGymnasium-v1-200-1686.hdf5",
        episode_length=1000,
        max_return=238.95831298828125,
        min_return=0.07114458084106445,
        max_cost=200.0,
    ),
    DSRLDataset(
        dataset_id="OfflineWalker2dVelocityGymnasium-v1",
        file_name="SafetyWalker2dVelocityGymnasium-v1-300-2729.hdf5",
        episode_length=1000,
        max_return=3418.223876953125,
        min_return=18.668498992919922,
        max_cost=300.0,
        observation_dim=17,
        action_dim=6,
        cost_threshold=40,
        return_threshold=2718.04,
        paper_name="Walker2dVelocity",
    ),
    # Safe MetaDrive
    DSRLDataset(
        dataset_id="OfflineMetadrive-easysparse-v0",
        file_name="SafeMetaDrive-easysparse-v0-85-1000.hdf5",
        episode_length=1000,
        max_return=425.8006286621094,
        min_return=20.094310760498047,
        max_cost=82.42418670654297,
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-easymean-v0",
        file_name="SafeMetaDrive-easymean-v0-85-1000.hdf5",
        episode_length=1000,
        max_return=425.82440185546875,
        min_return=22.142553329467773,
        max_cost=82.38601684570312,
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-easydense-v0",
        file_name="SafeMetaDrive-easydense-v0-85-1000.hdf5",
        episode_length=1000,
        max_return=425.81732177734375,
        min_return=19.71139144897461,
        max_cost=80.36358642578125,
        observation_dim=259,
        action_dim=2,
        cost_threshold=40,
        return_threshold=325.86,
        paper_name="MD-easydense",
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-mediumsparse-v0",
        file_name="SafeMetaDrive-mediumsparse-v0-50-1000.hdf5",
        episode_length=1000,
        max_return=269.80084228515625,
        min_return=17.446578979492188,
        max_cost=46.46459197998047,
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-mediummean-v0",
        file_name="SafeMetaDrive-mediummean-v0-50-1000.hdf5",
        episode_length=1000,
        max_return=269.8221435546875,
        min_return=17.032529830932617,
        max_cost=46.46154022216797,
        observation_dim=259,
        action_dim=2,
        cost_threshold=20,
        return_threshold=262.39,
        paper_name="MD-medianmean",
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-mediumdense-v0",
        file_name="SafeMetaDrive-mediumdense-v0-50-1000.hdf5",
        episode_length=1000,
        max_return=269.7813415527344,
        min_return=15.102348327636719,
        max_cost=46.45858383178711,
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-hardsparse-v0",
        file_name="SafeMetaDrive-hardsparse-v0-85-1000.hdf5",
        episode_length=1000,
        max_return=486.80523681640625,
        min_return=17.247974395751953,
        max_cost=85.010009765625,
        observation_dim=259,
        action_dim=2,
        cost_threshold=20,
        return_threshold=311.44,
        paper_name="MD-hardsparse",
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-hardmean-v0",
        file_name="SafeMetaDrive-hardmean-v0-85-1000.hdf5",
        episode_length=1000,
        max_return=486.9967956542969,
        min_return=19.387981414794922,
        max_cost=84.33995056152344,
    ),
    DSRLDataset(
        dataset_id="OfflineMetadrive-harddense-v0",
        file_name="SafeMetaDrive-harddense-v0-85-1000.hdf5",
        episode_length=1000,
        max_return=486.63616943359375,
        min_return=15.386894226074219,
        max_cost=84.76679229736328,
    ),
]

DSRL_DATASETS: dict[str, DSRLDataset] = {d.dataset_id: d for d in _DATASETS}


class UnknownDatasetError(KeyError):
    """A dataset id that is not in :data:`DSRL_DATASETS`."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def _match_key(name: str) -> str:
    """A name reduced to what tells datasets apart, for suggestions ("OfflinePointCircle1Gymnasium-v0" ->
    "pointcircle1")."""
    key = name.lower().removeprefix("offline").replace("gymnasium", "").replace("safety", "")
    return key.rsplit("-v", 1)[0].strip("-")


def get_dsrl_dataset(dataset_id: str) -> DSRLDataset:
    """Look up a DSRL dataset by id; an unknown id raises with the closest valid ids.

    Examples:
        >>> get_dsrl_dataset("OfflineCarCircle-v0").n_trajectories
        1450
        >>> get_dsrl_dataset("OfflinePointCircle1-v0")
        Traceback (most recent call last):
        ...
        spoil_torchrl.tasks.UnknownDatasetError: unknown DSRL dataset 'OfflinePointCircle1-v0'; did you mean \
'OfflinePointCircle1Gymnasium-v0', 'OfflinePointCircle2Gymnasium-v0', 'OfflineAntCircle-v0'?
    """
    if dataset_id in DSRL_DATASETS:
        return DSRL_DATASETS[dataset_id]
    by_key = {_match_key(d): d for d in DSRL_DATASETS}
    close = difflib.get_close_matches(_match_key(dataset_id), list(by_key), n=3, cutoff=0.0)
    suggestion = ", ".join(repr(by_key[c]) for c in close)
    raise UnknownDatasetError(f"unknown DSRL dataset {dataset_id!r}; did you mean {suggestion}?")


@dataclass(frozen=True)
class EnvTask:
    """A Safety-Gymnasium task the project simulates (collection, experts, evaluation).

    Attributes:
        env_id: Safety-Gymnasium id, e.g. ``"SafetyPointCircle1-v0"``.
        episode_length: time limit T of the registered environment.
        cost_limit: episode-cost limit of the constrained experts (paper Table G: 25).
        observation_dim, action_dim: sizes of the flat observation and action.
        cost_rule: the task's cost in words (checked by the tests).
        velocity_threshold: speed above which a velocity task costs 1 (``None`` for navigation tasks).
        dsrl_id: the matching DSRL dataset, for its normalisation constants.
        action_bound: every action coordinate lies in ``[-action_bound, action_bound]`` (the simulator's box,
            which the tanh-squashed policies span).
    """

    env_id: str
    episode_length: int
    cost_limit: float
    observation_dim: int
    action_dim: int
    cost_rule: str
    velocity_threshold: float | None = None
    dsrl_id: str | None = None
    action_bound: float = 1.0


# Sizes and cost rules: measured with safety-gymnasium 1.0.0; cost limit: Table G.
ENV_TASKS: dict[str, EnvTask] = {
    t.env_id: t
    for t in [
        EnvTask(
            "SafetyPointCircle1-v0",
            500,
            25.0,
            28,
            2,
            "cost 1 when |x| > 1.125",
            dsrl_id="OfflinePointCircle1Gymnasium-v0",
        ),
        EnvTask(
            "SafetyPointCircle2-v0",
            500,
            25.0,
            28,
            2,
            "cost 1 when |x| > 1.125 or |y| > 1.125",
            dsrl_id="OfflinePointCircle2Gymnasium-v0",
        ),
        EnvTask(
            "SafetyHopperVelocity-v1",
            1000,
            25.0,
            11,
            3,
            "cost 1 when x-velocity > 0.7402",
            0.7402,
            "OfflineHopperVelocityGymnasium-v1",
        ),
        EnvTask(
            "SafetyHalfCheetahVelocity-v1",
            1000,
            25.0,
            17,
            6,
            "cost 1 when x-velocity > 3.2096",
            3.2096,
            "OfflineHalfCheetahVelocityGymnasium-v1",
        ),
        EnvTask(
            "SafetyWalker2dVelocity-v1",
            1000,
            25.0,
            17,
            6,
            "cost 1 when x-velocity > 2.3415",
            2.3415,
            "OfflineWalker2dVelocityGymnasium-v1",
        ),
        EnvTask(
            "SafetyAntVelocity-v1",
            1000,
            25.0,
            27,
            8,
            "cost 1 when planar speed > 2.6222",
            2.6222,
            "OfflineAntVelocityGymnasium-v1",
        ),
    ]
}


def get_env_task(env_id: str) -> EnvTask:
    """Look up a simulated task; an unknown id raises with the closest ids.

    Examples:
        >>> get_env_task("SafetyPointCircle1-v0").episode_length
        500
    """
    if env_id in ENV_TASKS:
        return ENV_TASKS[env_id]
    close = difflib.get_close_matches(env_id, list(ENV_TASKS), n=3, cutoff=0.0)
    raise UnknownDatasetError(f"unknown task {env_id!r}; did you mean {', '.join(map(repr, close))}?")
