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


def _d(
    dataset_id, file_name, length, r_max, r_min, c_max, dims=(None, None), table_c=(None, None), paper=None
):
    return DSRLDataset(dataset_id, file_name, length, r_max, r_min, c_max, *dims, *table_c, paper)


_DATASETS = [
    # Bullet-Safety-Gym
    _d(
        "OfflineAntCircle-v0",
        "SafetyAntCircle-v0-200-5728.hdf5",
        500,
        460.7091979980469,
        0.0177031010389328,
        200.0,
        (33, 8),
        (40, 225.71),
        "AntCircle",
    ),
    _d(
        "OfflineAntRun-v0",
        "SafetyAntRun-v0-150-1816.hdf5",
        200,
        955.4818725585938,
        0.001767391717990563,
        150.0,
        (34, 8),
        (40, 664.83),
        "AntRun",
    ),
    _d(
        "OfflineBallCircle-v0",
        "SafetyBallCircle-v0-80-886.hdf5",
        200,
        881.46337890625,
        0.38312244415283203,
        80.0,
        (7, 2),
        (40, 712.45),
        "BallCircle",
    ),
    _d(
        "OfflineBallRun-v0",
        "SafetyBallRun-v0-80-940.hdf5",
        100,
        1327.445556640625,
        26.339754104614258,
        80.0,
        (8, 2),
        (40, 556.19),
        "BallRun",
    ),
    # CarCircle: the paper's Table C says 7 observation dims, DSRL's infos.py says 8; unverified, so not checked.
    _d(
        "OfflineCarCircle-v0",
        "SafetyCarCircle-v0-100-1450.hdf5",
        300,
        534.3060913085938,
        3.484419822692871,
        100.0,
        (None, 2),
        (40, 435.21),
        "CarCircle",
    ),
    _d(
        "OfflineCarRun-v0",
        "SafetyCarRun-v0-40-651.hdf5",
        200,
        574.6533203125,
        204.28726196289062,
        40.0,
        (8, 2),
        (20, 566.21),
        "CarRun",
    ),
    _d(
        "OfflineDroneCircle-v0",
        "SafetyDroneCircle-v0-100-1923.hdf5",
        300,
        996.38916015625,
        207.794189453125,
        100.0,
        (17, 4),
        (40, 713.46),
        "DroneCircle",
    ),
    _d(
        "OfflineDroneRun-v0",
        "SafetyDroneRun-v0-140-1990.hdf5",
        200,
        682.8330078125,
        10.557029724121094,
        140.0,
        (18, 4),
        (40, 411.47),
        "DroneRun",
    ),
    # Safety-Gymnasium navigation
    _d(
        "OfflineCarButton1Gymnasium-v0",
        "SafetyCarButton1Gymnasium-v0-250-2656.hdf5",
        1000,
        44.420003345738984,
        0.0028926206826067613,
        250.0,
    ),
    _d(
        "OfflineCarButton2Gymnasium-v0",
        "SafetyCarButton2Gymnasium-v0-300-3755.hdf5",
        1000,
        41.99513815522894,
        0.001767391717990563,
        300.0,
    ),
    _d(
        "OfflineCarCircle1Gymnasium-v0",
        "SafetyCarCircle1Gymnasium-v0-250-1271.hdf5",
        500,
        24.94155502319336,
        8.037073135375977,
        250.0,
    ),
    _d(
        "OfflineCarCircle2Gymnasium-v0",
        "SafetyCarCircle2Gymnasium-v0-400-940.hdf5",
        500,
        25.950098037719727,
        5.113386154174805,
        398.0,
    ),
    _d(
        "OfflineCarGoal1Gymnasium-v0",
        "SafetyCarGoal1Gymnasium-v0-120-1671.hdf5",
        1000,
        39.907809198384705,
        0.012232819540852091,
        120.0,
    ),
    _d(
        "OfflineCarGoal2Gymnasium-v0",
        "SafetyCarGoal2Gymnasium-v0-200-4105.hdf5",
        1000,
        28.902897990056502,
        0.001032874531954775,
        200.0,
    ),
    _d(
        "OfflineCarPush1Gymnasium-v0",
        "SafetyCarPush1Gymnasium-v0-200-2871.hdf5",
        1000,
        16.304467598905237,
        0.013700173533941762,
        200.0,
    ),
    _d(
        "OfflineCarPush2Gymnasium-v0",
        "SafetyCarPush2Gymnasium-v0-250-4407.hdf5",
        1000,
        15.141648491514314,
        0.00029391133526335267,
        250.0,
    ),
    _d(
        "OfflinePointButton1Gymnasium-v0",
        "SafetyPointButton1Gymnasium-v0-200-2268.hdf5",
        1000,
        41.19301568767707,
        0.008822109034937853,
        200.0,
        (76, 2),
        (40, 27.12),
        "PointButton1",
    ),
    _d(
        "OfflinePointButton2Gymnasium-v0",
        "SafetyPointButton2Gymnasium-v0-250-3288.hdf5",
        1000,
        42.8985953616709,
        0.014114166087574098,
        250.0,
        (76, 2),
        (80, 29.75),
        "PointButton2",
    ),
    _d(
        "OfflinePointCircle1Gymnasium-v0",
        "SafetyPointCircle1Gymnasium-v0-200-1098.hdf5",
        500,
        61.72819519042969,
        20.067626953125,
        200.0,
        (28, 2),
        (40, 44.85),
        "PointCircle1",
    ),
    _d(
        "OfflinePointCircle2Gymnasium-v0",
        "SafetyPointCircle2Gymnasium-v0-300-895.hdf5",
        500,
        54.02184295654297,
        20.478347778320312,
        299.0,
        (28, 2),
        (80, 43.10),
        "PointCircle2",
    ),
    _d(
        "OfflinePointGoal1Gymnasium-v0",
        "SafetyPointGoal1Gymnasium-v0-100-2022.hdf5",
        1000,
        30.071114857340543,
        0.01196012764197707,
        100.0,
        (60, 2),
        (40, 21.67),
        "PointGoal1",
    ),
    _d(
        "OfflinePointGoal2Gymnasium-v0",
        "SafetyPointGoal2Gymnasium-v0-200-3442.hdf5",
        1000,
        27.717709787852737,
        0.002616959830266108,
        200.0,
        (60, 2),
        (80, 20.40),
        "PointGoal2",
    ),
    _d(
        "OfflinePointPush1Gymnasium-v0",
        "SafetyPointPush1Gymnasium-v0-150-2379.hdf5",
        1000,
        16.518654299293367,
        0.0014001545292344209,
        150.0,
    ),
    _d(
        "OfflinePointPush2Gymnasium-v0",
        "SafetyPointPush2Gymnasium-v0-200-3242.hdf5",
        1000,
        14.691039145644403,
        0.0012438183001730607,
        200.0,
    ),
    # Safety-Gymnasium velocity
    _d(
        "OfflineAntVelocityGymnasium-v1",
        "SafetyAntVelocityGymnasium-v1-250-2249.hdf5",
        1000,
        2976.276611328125,
        6.1519012451171875,
        250.0,
        (27, 8),
        (40, 2743.78),
        "AntVelocity",
    ),
    _d(
        "OfflineHalfCheetahVelocityGymnasium-v1",
        "SafetyHalfCheetahVelocityGymnasium-v1-250-2495.hdf5",
        1000,
        2806.93310546875,
        5.7509765625,
        250.0,
        (17, 6),
        (40, 2563.55),
        "HalfCheetahVelocity",
    ),
    _d(
        "OfflineHopperVelocityGymnasium-v1",
        "SafetyHopperVelocityGymnasium-v1-250-2240.hdf5",
        1000,
        1911.396728515625,
        37.05154800415039,
        250.0,
        (11, 3),
        (40, 1607.84),
        "HopperVelocity",
    ),
    _d(
        "OfflineSwimmerVelocityGymnasium-v1",
        "SafetySwimmerVelocityGymnasium-v1-200-1686.hdf5",
        1000,
        238.95831298828125,
        0.07114458084106445,
        200.0,
    ),
    _d(
        "OfflineWalker2dVelocityGymnasium-v1",
        "SafetyWalker2dVelocityGymnasium-v1-300-2729.hdf5",
        1000,
        3418.223876953125,
        18.668498992919922,
        300.0,
        (17, 6),
        (40, 2718.04),
        "Walker2dVelocity",
    ),
    # Safe MetaDrive
    _d(
        "OfflineMetadrive-easysparse-v0",
        "SafeMetaDrive-easysparse-v0-85-1000.hdf5",
        1000,
        425.8006286621094,
        20.094310760498047,
        82.42418670654297,
    ),
    _d(
        "OfflineMetadrive-easymean-v0",
        "SafeMetaDrive-easymean-v0-85-1000.hdf5",
        1000,
        425.82440185546875,
        22.142553329467773,
        82.38601684570312,
    ),
    _d(
        "OfflineMetadrive-easydense-v0",
        "SafeMetaDrive-easydense-v0-85-1000.hdf5",
        1000,
        425.81732177734375,
        19.71139144897461,
        80.36358642578125,
        (259, 2),
        (40, 325.86),
        "MD-easydense",
    ),
    _d(
        "OfflineMetadrive-mediumsparse-v0",
        "SafeMetaDrive-mediumsparse-v0-50-1000.hdf5",
        1000,
        269.80084228515625,
        17.446578979492188,
        46.46459197998047,
    ),
    _d(
        "OfflineMetadrive-mediummean-v0",
        "SafeMetaDrive-mediummean-v0-50-1000.hdf5",
        1000,
        269.8221435546875,
        17.032529830932617,
        46.46154022216797,
        (259, 2),
        (20, 262.39),
        "MD-medianmean",
    ),
    _d(
        "OfflineMetadrive-mediumdense-v0",
        "SafeMetaDrive-mediumdense-v0-50-1000.hdf5",
        1000,
        269.7813415527344,
        15.102348327636719,
        46.45858383178711,
    ),
    _d(
        "OfflineMetadrive-hardsparse-v0",
        "SafeMetaDrive-hardsparse-v0-85-1000.hdf5",
        1000,
        486.80523681640625,
        17.247974395751953,
        85.010009765625,
        (259, 2),
        (20, 311.44),
        "MD-hardsparse",
    ),
    _d(
        "OfflineMetadrive-hardmean-v0",
        "SafeMetaDrive-hardmean-v0-85-1000.hdf5",
        1000,
        486.9967956542969,
        19.387981414794922,
        84.33995056152344,
    ),
    _d(
        "OfflineMetadrive-harddense-v0",
        "SafeMetaDrive-harddense-v0-85-1000.hdf5",
        1000,
        486.63616943359375,
        15.386894226074219,
        84.76679229736328,
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
