"""Foxglove-ready rollout files: sim-time log times, agent poses, the constraint scene, frames, the layout."""

from __future__ import annotations

import base64
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.well_known import SchemaEncoding

from spoil_torchrl.eval import RolloutWriter, read_rollouts
from spoil_torchrl.eval import mcap_foxglove as fox
from spoil_torchrl.eval.mcap_io import (
    EPISODE_GAP_NS,
    EPISODE_TOPIC,
    IMAGE_TOPIC,
    SCENE_TOPIC,
    STEP_TOPIC,
    TF_TOPIC,
    TOPIC_SCHEMAS,
)
from spoil_torchrl.eval.mcap_reader import iter_messages
from spoil_torchrl.eval.mcap_resume import continue_rollouts
from tests.eval.test_mcap_io import EPISODES, LENGTHS, METADATA, THRESHOLD, check_episodes

ROOT = Path(__file__).resolve().parents[2]
LAYOUT = ROOT / "docs" / "foxglove" / "rollouts_layout.json"
DT = 0.02
needs_safety = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed"
)
CUBE = {"pose": fox.identity_pose(), "size": {"x": 1.0, "y": 1.0, "z": 1.0}, "color": fox.color(1, 0, 0)}
SCENE = [{"id": "box", "primitives": {"cubes": [CUBE]}}]


def _poses(n: int) -> np.ndarray:
    """A straight walk along x, heading +x."""
    return np.column_stack([np.arange(n) * 0.1, np.zeros((n, 5)), np.ones(n)])


def read_topics(path: Path) -> dict[str, list[tuple[int, dict, str]]]:
    """topic -> [(log time, decoded JSON, schema name)] in file order, with the plain seeking reader."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            assert schema.encoding == SchemaEncoding.JSONSchema and channel.message_encoding == "json"
            assert message.publish_time == message.log_time
            out.setdefault(channel.topic, []).append(
                (message.log_time, json.loads(message.data), schema.name)
            )
    return out


def check_file(path: Path) -> dict[str, list]:
    """Every message validates against its topic's schema; times strictly increase in file order."""
    topics = read_topics(path)
    for topic, messages in topics.items():
        for _, message, schema_name in messages:
            assert schema_name == TOPIC_SCHEMAS[topic]["title"]
            fox.validate_json(message, TOPIC_SCHEMAS[topic])
    with open(path, "rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    steps = [t for t, _, _ in topics[STEP_TOPIC]]
    assert times == sorted(times) and steps == sorted(set(steps))
    return topics


def write_with_poses(path: Path, finish: bool = True) -> RolloutWriter:
    writer = RolloutWriter(path, cost_threshold=THRESHOLD, metadata=METADATA, dt=DT)
    for i, ep in enumerate(EPISODES):
        writer.write_episode(ep, evaluation_step=1000 * (i // 2), scene=SCENE, poses=_poses(LENGTHS[i]))
    if finish:
        writer.finish()
    return writer


def test_sim_time_poses_and_scene(tmp_path):
    path = tmp_path / "r.mcap"
    write_with_poses(path)
    topics = check_file(path)
    assert len(topics[TF_TOPIC]) == sum(LENGTHS) and len(topics[SCENE_TOPIC]) == len(LENGTHS)
    assert IMAGE_TOPIC not in topics  # no frames given: no camera channel
    steps, summaries = topics[STEP_TOPIC], topics[EPISODE_TOPIC]
    start = 0
    for e, n in enumerate(LENGTHS):
        times = [t for t, _, _ in steps[start : start + n]]
        assert np.diff(times).tolist() == [round(DT * 1e9)] * (n - 1)  # dt in ns between consecutive steps
        assert summaries[e][0] == times[0] + n * round(DT * 1e9) and summaries[e][1]["dt"] == DT
        assert topics[SCENE_TOPIC][e][0] == times[0]  # the scene at each episode's first log time
        if e:
            assert times[0] == summaries[e - 1][0] + EPISODE_GAP_NS
        start += n
    # each step's pose has the step's log time; the transform is world -> agent
    assert [t for t, _, _ in topics[TF_TOPIC]] == [t for t, _, _ in steps]
    first = topics[TF_TOPIC][1][1]
    assert first["parent_frame_id"] == "world" and first["child_frame_id"] == "agent"
    assert first["translation"]["x"] == pytest.approx(0.1) and first["rotation"]["w"] == 1.0
    assert first["timestamp"] == fox.time_of(topics[TF_TOPIC][1][0])
    r = read_rollouts(path)  # the reader ignores the new topics
    check_episodes(r, range(4))
    assert r.steps["log_time"][0, :2].tolist() == [t for t, _, _ in steps[:2]]


def test_resume_keeps_poses_and_stays_monotonic(tmp_path):
    path = tmp_path / "r.mcap"
    writer = write_with_poses(path, finish=False)
    writer.add_step(
        [0.0] * 3, [0.0] * 2, reward=1.0, cost=0.0, evaluation_step=2000, pose=([0, 0, 0], [0, 0, 0, 1])
    )
    writer._stream.flush()  # killed mid-episode: no footer
    old_tf = [m.log_time for topic, m in iter_messages(path) if topic == TF_TOPIC]
    with continue_rollouts(path, until_step=0, cost_threshold=THRESHOLD, metadata=METADATA) as resumed:
        resumed.write_episode(EPISODES[2], evaluation_step=1000, dt=DT, scene=SCENE, poses=_poses(LENGTHS[2]))
    topics = check_file(path)  # monotonic across the resume
    assert read_rollouts(path).episodes["evaluation_step"].tolist() == [0, 0, 1000]
    kept = LENGTHS[0] + LENGTHS[1]
    assert [t for t, _, _ in topics[TF_TOPIC][:kept]] == old_tf[:kept]  # copied poses keep their times
    assert len(topics[TF_TOPIC]) == kept + LENGTHS[2] and len(topics[SCENE_TOPIC]) == 3
    assert topics[STEP_TOPIC][kept][0] == topics[EPISODE_TOPIC][1][0] + EPISODE_GAP_NS


def test_compressed_image_round_trip(tmp_path):
    image = np.zeros((24, 32, 3), dtype=np.uint8)
    image[:12, :, 0], image[:, 16:, 2] = 255, 200  # a red top half, a blue right half
    path = tmp_path / "frames.mcap"
    with RolloutWriter(path, cost_threshold=1.0, dt=DT) as writer:
        writer.add_step([0.0], [0.0], reward=0.0, cost=0.0, frame=image, frame_format="png")
        writer.add_step([0.0], [0.0], reward=0.0, cost=0.0, frame=image)  # jpeg
        writer.end_episode()
    frames = check_file(path)[IMAGE_TOPIC]
    assert [m["format"] for _, m, _ in frames] == ["png", "jpeg"] and frames[0][
        2
    ] == "foxglove.CompressedImage"
    png, jpeg = (fox.decode_image(base64.b64decode(m["data"])) for _, m, _ in frames)
    assert np.array_equal(png, image)  # lossless
    assert jpeg.shape == image.shape and np.abs(jpeg.astype(int) - image).mean() < 8
    with pytest.raises(ValueError, match="uint8"):
        fox.encode_image(image.astype(np.float32))
    with pytest.raises(ValueError, match="image format"):
        fox.encode_image(image, "gif")


def test_validator_rejects_bad_messages():
    good = fox.scene_update(5, SCENE)
    fox.validate_json(good, fox.SCENE_UPDATE_SCHEMA)
    bad = json.loads(json.dumps(good))
    del bad["entities"][0]["cubes"][0]["color"]["a"]
    with pytest.raises(ValueError, match=r"\$.entities\[0\].cubes\[0\].color.a is missing"):
        fox.validate_json(bad, fox.SCENE_UPDATE_SCHEMA)
    line = {
        "type": 3,
        "pose": fox.identity_pose(),
        "thickness": 0.1,
        "scale_invariant": False,
        "points": [],
        "color": fox.color(0, 0, 0),
        "colors": [],
        "indices": [],
    }
    entity = fox.scene_entity("line", 5, lines=[line])
    with pytest.raises(ValueError, match=r"lines\[0\].type = 3 is not one of \[0, 1, 2\]"):
        fox.validate_json({"deletions": [], "entities": [entity]}, fox.SCENE_UPDATE_SCHEMA)


def _proto_fields(message) -> dict[str, set[str]]:
    """Foxglove SDK's protobuf schema of ``message``: message name -> field names."""
    from google.protobuf import descriptor_pb2

    files = descriptor_pb2.FileDescriptorSet.FromString(bytes(message.get_schema().data))
    return {f"foxglove.{m.name}": {fd.name for fd in m.field} for fp in files.file for m in fp.message_type}


def _json_fields(schema: dict, out: dict) -> dict[str, set[str]]:
    if schema.get("type") == "array":
        return _json_fields(schema["items"], out)
    if schema.get("type") == "object" and schema.get("title", "").startswith("foxglove."):
        out.setdefault(schema["title"], set()).update(schema["properties"])
        for spec in schema["properties"].values():
            _json_fields(spec, out)
    return out


def test_schemas_have_the_fields_of_foxglove_sdk():
    """Field names of our hand-written schemas are those of the SDK's definitions (less provenance fields)."""
    pytest.importorskip("google.protobuf")
    schemas = pytest.importorskip("foxglove.messages")
    for message, schema in (
        (schemas.FrameTransform(), fox.FRAME_TRANSFORM_SCHEMA),
        (schemas.SceneUpdate(), fox.SCENE_UPDATE_SCHEMA),
        (schemas.CompressedImage(), fox.COMPRESSED_IMAGE_SCHEMA),
    ):
        sdk = _proto_fields(message)
        for name, fields in _json_fields(schema, {}).items():
            assert fields == sdk[name] - {"message_id", "lineage"}, name


def test_layout_file_matches_the_topics():
    layout = json.loads(LAYOUT.read_text())
    panels = layout["configById"]

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    three_d = next(c for k, c in panels.items() if k.startswith("3D!"))
    assert three_d["followTf"] == fox.AGENT_FRAME and set(three_d["topics"]) == {TF_TOPIC, SCENE_TOPIC}
    plotted = {p["value"] for k, c in panels.items() if k.startswith("Plot!") for p in c["paths"]}
    assert {"/eval/step.reward", "/eval/step.cost", "/eval/step.cumulative_cost"} <= plotted
    for path in plotted:
        topic, field = path.split(".", 1)
        assert field.split(".")[0] in TOPIC_SCHEMAS[topic]["properties"], path


# -- with the simulator ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def circle_policy():
    from spoil_torchrl.zoo import load_policy, zoo_policy

    return load_policy(zoo_policy("SafetyPointCircle1-v0", "unsafe-high"))[0]


@needs_safety
def test_control_timestep_pose_and_boundary_come_from_the_env():
    from spoil_torchrl.envs import make_safety_gymnasium
    from spoil_torchrl.eval.env_scene import agent_pose, constraint_scene, control_timestep

    env = make_safety_gymnasium("SafetyPointCircle1-v0")
    env.reset(seed=0)
    task = env.unwrapped.task
    before = task.data.time
    env.step(np.zeros(2))
    assert control_timestep(env) == pytest.approx(task.data.time - before) == pytest.approx(0.02)  # measured
    pose = agent_pose(env)
    assert np.allclose(pose[:3], task.agent.pos) and np.isclose(np.linalg.norm(pose[3:]), 1.0)
    heading = np.arctan2(2 * pose[6] * pose[5], 1 - 2 * pose[5] ** 2)  # yaw of (0, 0, qz, qw)
    assert np.allclose([np.cos(heading), np.sin(heading)], task.agent.mat[:2, 0])  # the body's x axis
    scene = {e["id"]: e["primitives"] for e in constraint_scene(env)}
    walls = scene[f"boundary_walls_at_{task.sigwalls.locate_factor:g}"]["cubes"]
    assert sorted(c["pose"]["position"]["x"] for c in walls) == [-1.125, 1.125]
    circle = scene["reward_circle"]["lines"][0]["points"]
    assert np.allclose([np.hypot(p["x"], p["y"]) for p in circle], task.circle.radius)
    cheetah = make_safety_gymnasium("SafetyHalfCheetahVelocity-v1")
    cheetah.reset(seed=0)
    assert control_timestep(cheetah) == pytest.approx(0.05) and constraint_scene(cheetah) == []
    assert np.allclose(agent_pose(cheetah)[[0, 2]], cheetah.unwrapped.data.body("torso").xpos[[0, 2]])
    env.close(), cheetah.close()


@needs_safety
def test_evaluation_file_is_foxglove_ready(tmp_path, circle_policy):
    from spoil_torchrl.eval import Evaluator

    path = tmp_path / "rollouts.mcap"
    kwargs = dict(
        cost_threshold=25.0, return_range=(0.0, 40.0), episodes=3, num_envs=2
    )  # 3rd: unseeded reset
    with RolloutWriter(path, cost_threshold=25.0) as writer:
        evaluator = Evaluator("SafetyPointCircle1-v0", writer=writer, **kwargs)
        assert not evaluator.frames  # frames are off by default
        evaluator(circle_policy, step=10)
        evaluator(circle_policy, step=20)
    with continue_rollouts(path, until_step=10, cost_threshold=25.0) as writer:  # a resumed run
        Evaluator("SafetyPointCircle1-v0", writer=writer, **kwargs)(circle_policy, step=20)
    topics = check_file(path)  # schemas valid, times strictly increasing across evaluations and the resume
    assert IMAGE_TOPIC not in topics
    steps, poses = topics[STEP_TOPIC], topics[TF_TOPIC]
    assert len(steps) == len(poses) == 6 * 500 and len(topics[SCENE_TOPIC]) == 6
    assert [t for t, _, _ in steps] == [t for t, _, _ in poses]
    assert np.diff([t for t, _, _ in steps[:500]]).tolist() == [20_000_000] * 499
    assert [m["evaluation_step"] for _, m, _ in topics[EPISODE_TOPIC]] == [10] * 3 + [20] * 3
    # the pose is the state's: the cost of step t is 1 iff the next state is beyond |x| = 1.125
    for e in range(6):
        x = np.array([m["translation"]["x"] for _, m, _ in poses[500 * e : 500 * (e + 1)]])
        cost = np.array([m["cost"] for _, m, _ in steps[500 * e : 500 * (e + 1)]])
        assert np.array_equal(cost[:-1] > 0, np.abs(x[1:]) > 1.125), e
    assert sum(m["cost"] for _, m, _ in steps) > 0  # the unsafe expert leaves the boundary
    ids = {e["id"] for e in topics[SCENE_TOPIC][0][1]["entities"]}
    assert ids == {"reward_circle", "boundary_walls_at_1.125"}


@needs_safety
def test_poses_recorded_in_the_rollout_are_the_replays(circle_policy):
    """An evaluation without frames reads the agent's pose during its rollout instead of replaying it."""
    from spoil_torchrl.envs.rollout import episode_bounds, rollout
    from spoil_torchrl.eval.env_scene import agent_pose, replay_episodes

    arrays = rollout(
        "SafetyPointCircle1-v0", circle_policy, 3, seed=4, num_envs=2, progress=False, record=agent_pose
    )
    recorded = np.split(arrays.pop("recorded"), episode_bounds(arrays)[1][:-1])
    replayed, _ = replay_episodes("SafetyPointCircle1-v0", arrays, seed=4, num_envs=2)
    assert [p.shape for p in recorded] == [p.shape for p in replayed] == [(500, 7)] * 3
    for mine, theirs in zip(recorded, replayed, strict=True):
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-9)
    plain = rollout("SafetyPointCircle1-v0", circle_policy, 3, seed=4, num_envs=2, progress=False)
    assert all(np.array_equal(plain[key], arrays[key]) for key in plain)  # recording changes nothing


@needs_safety
def test_rendered_frames(tmp_path, circle_policy):
    from spoil_torchrl.eval.env_scene import make_render_env, replay_episodes

    try:
        make_render_env("SafetyPointCircle1-v0", 24).close()
    except RuntimeError as err:
        assert "MUJOCO_GL" in str(err)  # the one clear error; nothing more to test without OpenGL
        pytest.skip(f"no off-screen OpenGL here: {err}")
    from spoil_torchrl.envs.rollout import rollout

    arrays = rollout(
        "SafetyPointCircle1-v0", circle_policy, 1, seed=3, num_envs=1, deterministic=True, progress=False
    )
    poses, frames = replay_episodes(
        "SafetyPointCircle1-v0", arrays, seed=3, num_envs=1, frames=True, frame_size=24
    )
    assert poses[0].shape == (500, 7) and len(frames[0]) == 500 and frames[0][0].shape == (24, 24, 3)
    path = tmp_path / "frames.mcap"
    with RolloutWriter(path, cost_threshold=25.0, dt=0.02) as writer:
        from spoil_torchrl.eval import pad_episodes

        writer.write_episode(pad_episodes(arrays)[0], poses=poses[0], frames=frames[0])
    images = check_file(path)[IMAGE_TOPIC]
    assert len(images) == 500 and fox.decode_image(base64.b64decode(images[0][1]["data"])).shape == (
        24,
        24,
        3,
    )
