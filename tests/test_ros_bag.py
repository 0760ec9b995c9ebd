"""ROS bag import: bags written with rosbags' own writers (ROS1 and ROS2), read back into a Recording."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from usdeform.cli import main
from usdeform.errors import InputError
from usdeform.io import read_sequence
from usdeform.io.ros_bag import read_bag
from usdeform.recording import image_to_probe_from_geometry

pytest.importorskip("rosbags", reason="the ROS bag importer's optional dependency (in the test extra)")
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

ROWS, COLS = 24, 32
IMAGE_TIMES = 10.0 + np.arange(12) / 10.0  # 10 Hz images from t = 10 s
FORCE_TIMES = 9.95 + np.arange(150) / 100.0  # 100 Hz force, 9.95-11.44 s
POSE_TIMES = 9.98 + np.arange(41) / 40.0  # 40 Hz poses, 9.98-10.98 s: the last two images fall outside


def force_at(t):
    """Contact force, N: a ramp from 1 N."""
    return 1.0 + 4.0 * (t - 10.0)


def probe_to_base_at(t):
    """The probe presses 3 mm/s along its axis (tilted 20 degrees about x), from (10, 20, 30) mm."""
    rotation = Rotation.from_euler("x", 20, degrees=True)
    pose = np.eye(4)
    pose[:3, :3] = rotation.as_matrix()
    pose[:3, 3] = np.array([10.0, 20.0, 30.0]) + 3.0 * (t - 10.0) * rotation.as_matrix()[:, 2]
    return pose


def frame_at(i):
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, (ROWS, COLS), dtype=np.uint8)


def _stamp(types, t, ros1):
    time = types["builtin_interfaces/msg/Time"](sec=int(t), nanosec=round((t - int(t)) * 1e9))
    if ros1:
        return types["std_msgs/msg/Header"](seq=0, stamp=time, frame_id="probe")
    return types["std_msgs/msg/Header"](stamp=time, frame_id="probe")


TOPICS = {"image": "/us/image", "force": "/ft/wrench", "pose": "/robot/probe_pose"}


def messages(types, ros1, *, compressed=False, tf=False, force_sign=1.0, stamps=None):
    """(topic, msgtype, time ns, message) of the three streams, images in colour (bgr8) or PNG; ``stamps``:
    {stream: function (index, time) -> header stamp, s} for streams whose header stamps differ from their times."""
    stamps = stamps or {}
    out = []
    for i, t in enumerate(IMAGE_TIMES):
        header = _stamp(types, stamps.get("image", lambda i, t: t)(i, t), ros1)
        frame = frame_at(i)
        if compressed:
            png = np.frombuffer(cv2.imencode(".png", frame)[1].tobytes(), np.uint8)
            message = types["sensor_msgs/msg/CompressedImage"](header=header, format="png", data=png)
            out.append(("/us/image", "sensor_msgs/msg/CompressedImage", t, message))
        else:
            bgr = np.repeat(frame[:, :, None], 3, axis=2)
            message = types["sensor_msgs/msg/Image"](
                header=header,
                height=ROWS,
                width=COLS,
                encoding="bgr8",
                is_bigendian=0,
                step=COLS * 3,
                data=bgr.reshape(-1),
            )
            out.append(("/us/image", "sensor_msgs/msg/Image", t, message))
    for i, t in enumerate(FORCE_TIMES):
        stamp = stamps.get("force", lambda i, t: t)(i, t)
        vector = types["geometry_msgs/msg/Vector3"](x=0.3, y=-0.2, z=force_sign * force_at(t))
        wrench = types["geometry_msgs/msg/Wrench"](
            force=vector, torque=types["geometry_msgs/msg/Vector3"](x=0, y=0, z=0)
        )
        out.append(
            (
                "/ft/wrench",
                "geometry_msgs/msg/WrenchStamped",
                t,
                types["geometry_msgs/msg/WrenchStamped"](header=_stamp(types, stamp, ros1), wrench=wrench),
            )
        )
    for i, t in enumerate(POSE_TIMES):
        stamp = stamps.get("pose", lambda i, t: t)(i, t)
        pose = probe_to_base_at(t)
        x, y, z = pose[:3, 3] / 1000.0
        qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
        if tf:

            def transform(child, x, y, z, qx, qy, qz, qw, stamp=stamp):
                return types["geometry_msgs/msg/TransformStamped"](
                    header=_stamp(types, stamp, ros1),
                    child_frame_id=child,
                    transform=types["geometry_msgs/msg/Transform"](
                        translation=types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
                        rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                    ),
                )

            camera = transform("camera", 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # another frame on /tf: ignored
            message = types["tf2_msgs/msg/TFMessage"](transforms=[camera, transform("probe", x, y, z, qx, qy, qz, qw)])
            out.append(("/tf", "tf2_msgs/msg/TFMessage", t, message))
        else:
            message = types["geometry_msgs/msg/PoseStamped"](
                header=_stamp(types, stamp, ros1),
                pose=types["geometry_msgs/msg/Pose"](
                    position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                    orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
            out.append(("/robot/probe_pose", "geometry_msgs/msg/PoseStamped", t, message))
    return sorted(out, key=lambda item: item[2])


def write_bag(path: Path, ros1: bool, **options) -> Path:
    if ros1:
        typestore = get_typestore(Stores.ROS1_NOETIC)
        # ROS1's /tf type is not in rosbags' noetic store: register it from its message definition.
        typestore.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        path = path.with_suffix(".bag")
        writer = Writer1(path)
        serialize = typestore.serialize_ros1
    else:
        typestore = get_typestore(Stores.ROS2_HUMBLE)
        writer = Writer2(path, version=9)
        serialize = typestore.serialize_cdr
    connections = {}
    with writer:
        for topic, msgtype, t, message in messages(typestore.types, ros1, **options):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            writer.write(connections[topic], int(t * 1e9), serialize(message, msgtype))
    return path


def check_recording(recording, n_kept=10):
    """The first 10 images have poses within the tolerance; the last two do not."""
    assert len(recording) == n_kept
    np.testing.assert_array_equal(recording.frames, np.stack([frame_at(i) for i in range(n_kept)]))
    np.testing.assert_allclose(recording.timestamps, IMAGE_TIMES[:n_kept] - IMAGE_TIMES[0], atol=1e-6)
    np.testing.assert_allclose(recording.force, force_at(IMAGE_TIMES[:n_kept]), atol=1e-6)
    expected = np.stack([probe_to_base_at(t) for t in IMAGE_TIMES[:n_kept]])
    np.testing.assert_allclose(recording.probe_to_base, expected, atol=1e-6)
    np.testing.assert_allclose(recording.probe_displacement, 3.0 * (IMAGE_TIMES[:n_kept] - 10.0), atol=1e-6)


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
@pytest.mark.parametrize(("compressed", "tf"), [(False, False), (True, True)], ids=["raw-pose", "png-tf"])
def test_bag_streams_are_matched_to_the_image_times(tmp_path, ros1, compressed, tf):
    bag = write_bag(tmp_path / "palpation", ros1, compressed=compressed, tf=tf)
    calibration = image_to_probe_from_geometry(ROWS, COLS)
    imported = read_bag(
        bag,
        image_topic="/us/image",
        force_topic="/ft/wrench",
        pose_topic="/tf" if tf else "/robot/probe_pose",
        pose_child_frame="probe" if tf else None,
        image_to_probe=calibration,
        tolerance_s=0.05,
    )
    assert imported.n_images == 12
    assert imported.dropped == {"force": 0, "pose": 2}
    assert imported.warnings == []
    check_recording(imported.recording)
    np.testing.assert_array_equal(imported.recording.image_to_probe, calibration)


def test_import_bag_command_writes_a_sequence_the_pipeline_reads(tmp_path, capsys):
    bag = write_bag(tmp_path / "palpation", ros1=False, force_sign=-1.0)
    output = tmp_path / "palpation.seq.nrrd"
    main(
        [
            "import-bag",
            str(bag),
            "--output",
            str(output),
            "--image-topic",
            "/us/image",
            "--force-topic",
            "/ft/wrench",
            "--pose-topic",
            "/robot/probe_pose",
            "--force-axis=-z",
            "--depth-mm",
            "40",
            "--width-mm",
            "37.5",
        ]
    )
    printed = capsys.readouterr().out
    assert "imported 10 of 12 frames" in printed and "2 without pose" in printed
    recording = read_sequence(output)
    check_recording(recording)
    np.testing.assert_allclose(recording.image_to_probe, image_to_probe_from_geometry(ROWS, COLS), atol=1e-9)


def test_a_reversed_force_axis_is_reported(tmp_path):
    bag = write_bag(tmp_path / "palpation", ros1=True, force_sign=-1.0)
    imported = read_bag(
        bag,
        image_topic="/us/image",
        force_topic="/ft/wrench",
        pose_topic="/robot/probe_pose",
        image_to_probe=np.eye(4),
    )
    assert len(imported.warnings) == 1 and "force_axis='-z'" in imported.warnings[0]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"image_topic": "/nope"}, "image topic '/nope' is not in the bag"),
        ({"force_topic": "/us/image"}, "force topic '/us/image' carries sensor_msgs/msg/Image"),
        ({"pose_topic": "/ft/wrench"}, "pose topic '/ft/wrench' carries geometry_msgs/msg/WrenchStamped"),
        ({"tolerance_s": 0.0}, "tolerance_s"),
        ({"tolerance_s": 1e-4}, "no image has force and pose samples within 0.0001 s"),
    ],
)
def test_bad_topics_and_tolerances_are_named(tmp_path, options, message):
    bag = write_bag(tmp_path / "palpation", ros1=False)
    arguments = {
        "image_topic": "/us/image",
        "force_topic": "/ft/wrench",
        "pose_topic": "/robot/probe_pose",
        "image_to_probe": np.eye(4),
        **options,
    }
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(".", r"\.")):
        read_bag(bag, **arguments)


def test_a_missing_bag_is_named(tmp_path):
    with pytest.raises(InputError, match="no such bag"):
        read_bag(tmp_path / "none.bag", image_topic="a", force_topic="b", pose_topic="c", image_to_probe=np.eye(4))


def _read(bag):
    return read_bag(
        bag, image_topic="/us/image", force_topic="/ft/wrench", pose_topic="/robot/probe_pose", image_to_probe=np.eye(4)
    )


@pytest.mark.parametrize("stamp", [12.5, 1e9], ids=["12.5 s", "1e9 s"])
@pytest.mark.parametrize("stream", list(TOPICS))
@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_a_stream_whose_messages_share_one_header_stamp_is_refused(tmp_path, capsys, ros1, stream, stamp):
    """Issue 43: every image stamped alike gave 12 frames at t = 0 with one force and exit 0."""
    bag = write_bag(tmp_path / "palpation", ros1=ros1, stamps={stream: lambda i, t: stamp})
    with pytest.raises(InputError, match=rf"{stream} topic '{TOPICS[stream]}': all \d+ messages carry the same header"):
        _read(bag)
    output = tmp_path / "out.seq.nrrd"
    argv = ["import-bag", str(bag), "--output", str(output), "--depth-mm", "40", "--width-mm", "37.5"]
    argv += [f"--{name}-topic={topic}" for name, topic in TOPICS.items()]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("usdeform: error: ") and TOPICS[stream] in err and "\n" not in err
    assert not output.exists()


@pytest.mark.parametrize("stream", list(TOPICS))
def test_repeated_header_stamps_keep_the_first_message_with_a_warning(tmp_path, stream):
    """Two messages of one stream with one stamp (a duplicated message): the first is used, with a warning."""
    times = {"image": IMAGE_TIMES, "force": FORCE_TIMES, "pose": POSE_TIMES}[stream]
    bag = write_bag(tmp_path / "palpation", ros1=False, stamps={stream: lambda i, t: times[3] if i == 4 else t})
    imported = _read(bag)
    assert any(f"{stream} topic '{TOPICS[stream]}': 1 of" in warning for warning in imported.warnings)
    if stream == "image":  # image 4 is left out
        kept = [0, 1, 2, 3, 5, 6, 7, 8, 9]
        np.testing.assert_array_equal(imported.recording.frames, np.stack([frame_at(i) for i in kept]))
