"""Sensor set-ups other than the sample's (image sizes, intrinsics, encodings, camera_info, voxel
sizes), each a small bag written with rosbags (`sensor_bags`) and replayed: the mesh lies on the
scene's surfaces, or what went wrong is said, counted and explained."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from senfunet_ros.bagio import open_bag
from odd_bags import spelled_both_ways, with_damaged_messages
from replays import replay_in_process
from sensor_bags import Camera, params_file, surface_distance_m, two, write_bag


def _replay(tmp_path: Path, recording, *, mesh_of: str = "mesh", **params):
    """(the command's output, stats.json, the vertices of the fused mesh, or with mesh_of a sensor's
    name of that sensor's mesh) of the recording's replay."""
    from senfunet_core.ply import read_ply

    bag = write_bag(recording, tmp_path / "bag")
    proc = replay_in_process(bag, tmp_path / "out", params_file(tmp_path / "params.yaml", recording, **params),
                             compare=mesh_of != "mesh")
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    mesh = tmp_path / "out" / f"{mesh_of}.ply"
    vertices = np.asarray(read_ply(mesh).vertices) if mesh.exists() else np.zeros((0, 3))
    return proc, stats, vertices


def test_replay_says_why_frames_were_dropped_and_that_distortion_is_not_applied(tmp_path: Path):
    """An uncalibrated camera_info (K all zero) and a distorted one: stats.json and the command's
    output say what was wrong, not only the reason's name, that the distortion is not applied, and
    that the fused mesh holds only what the net trusts of the sensor that was fused."""
    recording = two(Camera("tof", rate_hz=15.0, info_k=(0.0,) * 9),
                    Camera("stereo", x_m=0.05, color="rgb8", distortion_model="equidistant", d=(0.1, 0.01, 0.0, 0.0)))
    proc, stats, vertices = _replay(tmp_path, recording)
    assert proc.returncode == 0, proc.stderr
    tof, stereo = stats["sensors"]["tof"], stats["sensors"]["stereo"]
    assert tof["integrated"] == 0 and tof["dropped"]["bad_camera_info"] > 0
    assert "no positive finite focal lengths" in tof["errors"]["bad_camera_info"]
    assert "no positive finite focal lengths" in proc.stdout
    assert stereo["distorted"] is True and tof["distorted"] is False
    assert "stereo: note: its camera_info has non-zero distortion coefficients" in proc.stdout
    # one sensor alone: what the outlier filter leaves of it is said, not only an empty or sparse mesh.ply
    assert "note: tof fused no frame" in proc.stderr and "weighting net trusts" in proc.stderr, proc.stderr


def test_voxels_finer_than_the_sample_step_still_mesh_the_surface(tmp_path: Path):
    """5 mm voxels under the default 10 cm band: the paper's 11 samples lie 1 cm apart, two voxels, and
    skipped every other voxel along each ray; no cell had its 8 corners observed and the mesh was empty.
    The samples now stay a voxel apart (more of them): the mesh covers the surfaces seen."""
    dense = dict(width=128, height=96, fx=450.0, fy=450.0)  # pixels ~4 mm apart on the wall, below a voxel
    recording = two(Camera("tof", rate_hz=15.0, **dense), Camera("stereo", x_m=0.05, color="rgb8", **dense),
                    duration_s=0.3)
    proc, stats, vertices = _replay(tmp_path, recording, voxel_size_m=0.005)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert len(vertices) > 1000, stats["meshes"]
    assert np.quantile(surface_distance_m(vertices), 0.99) < 0.01


def test_a_band_narrower_than_two_voxels_is_refused_with_the_reason():
    from senfunet_ros.params_file import load_settings

    with pytest.raises(ValueError, match=r"band_m \(0.015 m\) must be at least two voxels"):
        load_settings(overrides={"voxel_size_m": 0.01, "band_m": 0.015})
    load_settings(overrides={"voxel_size_m": 0.01, "band_m": 0.02})


def test_a_camera_info_of_another_resolution_is_scaled_to_the_image_and_another_aspect_refused(tmp_path: Path):
    """The contract: camera_info's K, other resolutions resized and K scaled. A driver that decimates its
    depth (96x72) next to the full-resolution camera_info (192x144) had every frame dropped as
    size_mismatch; its K is now scaled to the image. A camera_info of another aspect ratio (a crop,
    another camera) cannot give the image's K: still dropped, saying so."""
    full = (120.0, 0.0, 95.5, 0.0, 120.0, 71.5, 0.0, 0.0, 1.0)  # the Camera's K (fx 60, centred) at twice the size
    recording = two(Camera("tof", rate_hz=15.0, info_size=(192, 144), info_k=full))
    proc, stats, vertices = _replay(tmp_path / "resized", recording)
    tof = stats["sensors"]["tof"]
    assert tof["integrated"] == tof["received"] > 0 and tof["dropped"]["size_mismatch"] == 0, proc.stdout
    assert len(vertices) > 1000 and np.quantile(surface_distance_m(vertices), 0.99) < 0.02
    cropped = two(Camera("tof", rate_hz=15.0, info_size=(192, 108), info_k=full))
    proc, stats, _ = _replay(tmp_path / "cropped", cropped)
    tof = stats["sensors"]["tof"]
    assert tof["integrated"] == 0 and tof["dropped"]["size_mismatch"] == tof["received"] > 0
    assert "another aspect ratio" in tof["errors"]["size_mismatch"]


def test_sensors_in_another_order_than_the_weights_are_refused_in_one_line_saying_why(tmp_path: Path):
    """The shipped weights take sensor 1 as depth only, sensor 2 with colour. Sensors listed the other way
    round (stereo first, still the colour one) failed on a tensor shape deep in torch, over two lines."""
    recording = two(Camera("stereo", color="rgb8"), Camera("tof", x_m=0.05, rate_hz=15.0))
    bag = write_bag(recording, tmp_path / "bag")
    proc = replay_in_process(bag, tmp_path / "out",
                             params_file(tmp_path / "params.yaml", recording, rgb_sensors=["stereo"]))
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "trained with sensor 1 depth only, sensor 2 depth and colour" in proc.stderr
    assert "this engine has sensor 1 depth and colour, sensor 2 depth only" in proc.stderr


@pytest.mark.parametrize("name, reason", [("mesh", "names an output"), ("tsdf_fusion", "names an output"),
                                          ("front cam", "not a usable sensor name"), ("", "not a usable sensor name"),
                                          ("cam/front", "not a usable sensor name")])
def test_a_sensor_name_that_cannot_name_its_topics_and_files_is_refused(ros, name: str, reason: str):
    """Sensor names from a parameter file: 'mesh' lost its mesh to the fused mesh (save_mesh and replay
    --compare wrote one mesh.ply for both); 'front cam' or '' crashed the live node on a topic name
    rclpy refuses (InvalidTopicNameException, a traceback). Both paths now refuse them saying why."""
    import rclpy
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode
    from senfunet_ros.params_file import load_settings

    with pytest.raises(ValueError, match=reason):
        load_settings(overrides={"sensors": [name, "stereo"]})
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros)
    try:
        with pytest.raises(ValueError, match=reason):
            FusionNode(context=context, parameter_overrides=[Parameter("sensors", value=[name, "stereo"]),
                                                             Parameter("weights", value="none")])
    finally:
        rclpy.try_shutdown(context=context)
    load_settings(overrides={"sensors": ["front_cam", "stereo"]})  # letters, digits and '_' are fine


def test_a_topic_parameter_that_is_no_topic_name_is_refused_naming_the_parameter(ros):
    """'/front cam/depth' from a parameter file crashed the live node with rclpy's InvalidTopicNameException
    and a traceback (not the one-line 'cannot start' of bad parameters)."""
    import rclpy
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode
    from senfunet_ros.params_file import load_settings

    reason = r"parameter 'tof.depth_topic' = '/front cam/depth' is not a topic name"
    with pytest.raises(ValueError, match=reason):
        load_settings(overrides={"tof.depth_topic": "/front cam/depth"})
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros)
    try:
        with pytest.raises(ValueError, match=reason):
            FusionNode(context=context, parameter_overrides=[Parameter("tof.depth_topic", value="/front cam/depth"),
                                                             Parameter("weights", value="none")])
    finally:
        rclpy.try_shutdown(context=context)
    load_settings(overrides={"stereo.color_topic": "", "tof.depth_topic": "camera/depth"})  # none; relative


def test_two_sensors_on_one_depth_topic_are_refused_but_may_share_a_pose_topic():
    """A parameter file whose tof topics were copied from stereo's: replay fused the stereo stream as both
    sensors (80 of 80 frames each), the tof topics ignored, without a word. One depth topic for two
    sensors is now refused; one odometry for a rig serves both, and 'cam/depth' beside '/cam/depth' are two
    topics in a namespace."""
    from senfunet_ros.params_file import load_settings

    with pytest.raises(ValueError, match=r"'tof.depth_topic' and 'stereo.depth_topic' name the same topic"):
        load_settings(overrides={"tof.depth_topic": "/stereo/depth", "stereo.depth_topic": "/stereo/depth"})
    load_settings(overrides={"tof.depth_topic": "cam/depth", "stereo.depth_topic": "/cam/depth"})
    settings = load_settings(overrides={"tof.pose_topic": "/odom", "stereo.pose_topic": "/odom",
                                        "pose_type": "odometry"})
    assert [sensor.pose_topic for sensor in settings.sensors] == ["/odom", "/odom"]


def test_rgb_sensors_naming_no_sensor_is_refused():
    """Sensors renamed in a parameter file, rgb_sensors left at its default [stereo]: no feature net took
    colour, silently (with untrained weights; the shipped ones failed on a tensor shape)."""
    from senfunet_ros.params_file import load_settings

    with pytest.raises(ValueError, match=r"'rgb_sensors' names \['stereo'\], not among sensors \['front', 'back'\]"):
        load_settings(overrides={"sensors": ["front", "back"], "weights": "none"})
    load_settings(overrides={"sensors": ["front", "back"], "rgb_sensors": ["back"]})


def test_a_colour_sensor_without_colour_is_said_in_replay_and_by_the_node(ros, tmp_path: Path, capfd):
    """The shipped weights' second sensor takes colour: a bag without its colour topic, or the node with
    its color_topic empty, fused its frames with black colour without a word."""
    import rclpy
    from rclpy.parameter import Parameter

    from senfunet_ros.node import FusionNode

    recording = two(Camera("tof", rate_hz=15.0), Camera("stereo", x_m=0.05, color=""))
    bag = write_bag(recording, tmp_path / "bag")
    params = params_file(tmp_path / "params.yaml", recording, **{"stereo.color_topic": "/stereo/color"})
    proc = replay_in_process(bag, tmp_path / "out", params)
    assert proc.returncode == 0, proc.stderr
    assert "stereo: note: stereo's feature net takes colour (rgb_sensors) but the bag has no messages on " \
        "/stereo/color" in proc.stdout
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros)
    try:
        capfd.readouterr()
        node = FusionNode(context=context, parameter_overrides=[Parameter("stereo.color_topic", value=""),
                                                                Parameter("weights", value="none"),
                                                                Parameter("output_dir", value=str(tmp_path))])
        node.destroy_node()
        said = capfd.readouterr().err
        assert "stereo's feature net takes colour (rgb_sensors) but stereo.color_topic is empty" in said
    finally:
        rclpy.try_shutdown(context=context)


def test_colour_of_another_aspect_ratio_is_refused_once_with_both_sizes_and_depth_fused_without_it(tmp_path: Path):
    """A colour camera of another aspect ratio (16:9 colour beside 4:3 depth, not registered to it) was
    stretched onto the depth without a word: every depth pixel took another point's colour. Now its
    frames are fused without colour, counted, and a note names both sizes and what to publish; colour
    of the same aspect ratio (twice the depth's size) is still resized onto the depth."""
    wide = two(Camera("tof", rate_hz=15.0), Camera("stereo", x_m=0.05, color="rgb8", color_size=(128, 72)))
    proc, stats, vertices = _replay(tmp_path / "wide", wide)
    assert proc.returncode == 0, proc.stderr
    stereo = stats["sensors"]["stereo"]
    assert stereo["integrated"] > 0 and stereo["color_refused"] == stereo["integrated"], stereo
    assert stereo["without_color"] == 0
    note = stereo["notes"]["color_size"]
    assert "colour images are 128x72 and the depth images 96x72" in note and "registered to the depth" in note
    assert proc.stdout.count("stereo: note: the colour images are 128x72") == 1, proc.stdout
    assert "fused without colour of another aspect ratio" in proc.stdout
    assert len(vertices) > 1000
    larger = two(Camera("tof", rate_hz=15.0), Camera("stereo", x_m=0.05, color="rgb8", color_size=(192, 144)))
    proc, stats, _ = _replay(tmp_path / "larger", larger)
    stereo = stats["sensors"]["stereo"]
    assert stereo["integrated"] > 0 and stereo["color_refused"] == 0 and "color_size" not in stereo["notes"]


def test_a_camera_info_whose_k_fits_the_image_but_not_its_size_keeps_its_k_and_says_so(tmp_path: Path):
    """A driver that decimates its images and K but leaves width and height at the full resolution
    (192x144 said, 96x72 sent, K for 96x72): K was scaled to half (fx 30, principal point at a quarter
    of the image): the ToF's surfaces, placed off the stereo's, were all filtered out of its mesh (0
    vertices in tof.ply). The principal point tells: as given it is at the image's centre, scaled it is
    not; K is taken as given and a note names the sizes, both Ks and what to fix. A K that is the full
    resolution's (the earlier test) is still scaled, silently."""
    camera = Camera("tof", rate_hz=15.0, info_size=(192, 144))  # info_k: None, the K of the 96x72 images
    proc, stats, vertices = _replay(tmp_path, two(camera), mesh_of="tof")
    assert proc.returncode == 0, proc.stderr
    tof = stats["sensors"]["tof"]
    assert tof["integrated"] == tof["received"] > 0
    assert len(vertices) > 1000 and np.quantile(surface_distance_m(vertices), 0.99) < 0.02
    note = tof["notes"]["camera_info_size"]
    assert "says 192x144 but the depth images are 96x72" in note
    assert "fx 60, fy 60, cx 47.5, cy 35.5" in note and "fx 30, fy 30, cx 23.5, cy 17.5" in note
    assert "Fix the driver's camera_info (width 96, height 72)" in note
    assert proc.stdout.count("tof: note: the camera_info says 192x144") == 1, proc.stdout
    full = (120.0, 0.0, 95.5, 0.0, 120.0, 71.5, 0.0, 0.0, 1.0)  # the full resolution's K: scaled, no note
    proc, stats, _ = _replay(tmp_path / "full", two(Camera("tof", rate_hz=15.0, info_size=(192, 144), info_k=full)))
    assert stats["sensors"]["tof"]["integrated"] > 0 and "camera_info_size" not in stats["sensors"]["tof"]["notes"]


def test_pixels_further_apart_than_a_voxel_are_said_once_per_sensor_with_what_to_change(tmp_path: Path):
    """96x72 images with fx 60 px see the wall 2 m away with pixels 33 mm apart: under 1 cm voxels the
    rays skip two voxels in three across the surface, and the mesh has holes, without a word. Each
    sensor's first frame now says so, with the spacing, the median depth and what to change. 2.5 cm
    voxels, 1.33 voxels' spacing, say nothing: a frame still observes most of a facing surface, and any
    motion fills the rest (the sample's pixels lie 1.04-1.1 voxels apart at the defaults)."""
    proc, stats, _ = _replay(tmp_path / "fine", two(), voxel_size_m=0.01)
    assert proc.returncode == 0, proc.stderr
    for sensor in ("tof", "stereo"):
        note = stats["sensors"][sensor]["notes"]["pixel_spacing"]
        assert "pixels lie 33.3 mm apart at its median depth 2.00 m" in note, note
        assert "more than the 10.0 mm voxels: a frame's rays observe about 9% of the voxels" in note
        assert "holes" in note
        assert "voxels of at least 33.3 mm (voxel_size_m)" in note and "a camera of at least 320 pixels" in note
        assert proc.stdout.count(f"{sensor}: note: its pixels lie") == 1, proc.stdout
    proc, stats, _ = _replay(tmp_path / "coarse", two(), voxel_size_m=0.025)
    assert proc.returncode == 0, proc.stderr
    assert all("pixel_spacing" not in c["notes"] for c in stats["sensors"].values()), stats["sensors"]


def test_the_live_node_warns_once_per_sensor_about_its_set_up(ros, tmp_path: Path, capfd):
    """The node takes the same messages (the bag's, as rclpy messages) through the same Ingest: colour
    of another aspect ratio, a camera_info whose K fits the image but not its size, and pixels
    further apart than 1.5 voxels are each warned about once per sensor, however many frames follow."""
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message

    from senfunet_ros.bagio import message_class, open_bag
    from senfunet_ros.node import FusionNode

    recording = two(Camera("tof", rate_hz=15.0, info_size=(192, 144)),
                    Camera("stereo", x_m=0.05, color="rgb8", color_size=(128, 72)))
    bag = write_bag(recording, tmp_path / "bag")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros)
    try:
        node = FusionNode(context=context, parameter_overrides=[
            Parameter("weights", value="none"), Parameter("working_width", value=0),
            Parameter("voxel_size_m", value=0.01), Parameter("output_dir", value=str(tmp_path))])
        try:
            capfd.readouterr()
            add = {"depth": node.ingest.add_depth, "color": node.ingest.add_color,
                   "camera_info": node.ingest.add_camera_info, "pose": node.ingest.add_pose}
            with open_bag(bag) as reader:
                for i, message in enumerate(reader.messages(None)):
                    sensor, stream = message.topic.strip("/").split("/")
                    add[stream](sensor, deserialize_message(message.data, message_class(message.msgtype)))
                    if i % 10 == 0:
                        node._integrate_tick()  # the node's integration timer's work
            node._integrate_tick()
            counters = node.ingest.ledger.counters()
            said = capfd.readouterr().err
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert counters["stereo"]["color_refused"] == counters["stereo"]["integrated"] > 1
    assert counters["tof"]["integrated"] > 1
    assert said.count("stereo: the colour images are 128x72 and the depth images 96x72") == 1, said
    assert said.count("tof: the camera_info says 192x144 but the depth images are 96x72") == 1, said
    for sensor in ("tof", "stereo"):
        assert said.count(f"{sensor}: its pixels lie 33.3 mm apart") == 1, said


def test_topics_recorded_with_and_without_their_leading_slash_are_one_topic(tmp_path: Path):
    """Two recordings merged, one naming its topics 'tof/depth', the other '/tof/depth': one topic
    (`bagio.absolute_topic`). Replay fused only one spelling's messages, without a word; the other's were
    listed under ignored_topics."""
    recording = two(duration_s=0.6)
    bag = spelled_both_ways(write_bag(recording, tmp_path / "plain"), tmp_path / "bag")
    with open_bag(bag) as reader:
        depth_counts = {topic: info.count for topic, info in reader.topics.items() if topic.endswith("depth")}
    assert set(depth_counts) == {"tof/depth", "/tof/depth", "stereo/depth", "/stereo/depth"}, depth_counts
    proc = replay_in_process(bag, tmp_path / "out", params_file(tmp_path / "params.yaml", recording))
    assert proc.returncode == 0, proc.stderr
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["ignored_topics"] == {}, stats["ignored_topics"]
    for sensor in ("tof", "stereo"):
        received = depth_counts[f"{sensor}/depth"] + depth_counts[f"/{sensor}/depth"]
        assert stats["sensors"][sensor]["received"] == received, (sensor, stats["sensors"][sensor])
        assert stats["sensors"][sensor]["integrated"] >= received - 1, (sensor, stats["sensors"][sensor])
    assert stats["topics"]["/tof/depth"]["sensor"] == "tof"


def test_colour_that_cannot_be_decoded_at_all_is_said_as_no_colour_and_counted(tmp_path: Path):
    """Every colour message of the colour sensor damaged (cut short): its frames were fused with black colour,
    without_color 0 and no note, only the count of undecodable messages. Now the note a bag without colour
    gets, and every frame counted as fused without colour."""
    recording = two()
    bag = with_damaged_messages(write_bag(recording, tmp_path / "plain"), tmp_path / "bag",
                                lambda topic, n, data: data[:100] if topic == "/stereo/color" else data)
    proc = replay_in_process(bag, tmp_path / "out", params_file(tmp_path / "params.yaml", recording))
    assert proc.returncode == 0, proc.stderr
    stereo = json.loads((tmp_path / "out" / "stats.json").read_text())["sensors"]["stereo"]
    assert stereo["integrated"] > 0 and stereo["without_color"] == stereo["integrated"], stereo
    assert stereo["color_usable"] == 0 and stereo["undecodable"]["color"] > 0, stereo
    assert ("stereo: note: stereo's feature net takes colour (rgb_sensors) but none of the colour images on "
            "/stereo/color could be decoded: its frames are fused with black colour") in proc.stdout, proc.stdout


def test_what_replay_says_as_it_goes_is_in_stats_json_and_a_bag_without_colour_counts_its_frames(tmp_path: Path):
    """A colour sensor's bag without colour, and a map bound below what a frame sees: replay printed a note
    and a warning, while stats.json had `warnings` [], `notes` {} and `without_color` 0. The warning is now
    in `warnings`, the note in the sensor's `notes` (printed once, with the sensor's), and every frame
    counts as fused without colour. (The colour topic is given relative: it is the same topic.)"""
    recording = two(second=Camera("stereo", x_m=0.05))  # no colour images
    params = params_file(tmp_path / "params.yaml", recording, **{"stereo.color_topic": "stereo/color"},
                         max_map_blocks=10)
    proc = replay_in_process(write_bag(recording, tmp_path / "bag"), tmp_path / "out", params)
    assert proc.returncode == 0, proc.stderr
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    stereo = stats["sensors"]["stereo"]
    assert stereo["integrated"] > 0 and stereo["without_color"] == stereo["integrated"], stereo
    assert "the bag has no messages on /stereo/color" in stereo["notes"]["colourless"], stereo["notes"]
    assert (proc.stdout + proc.stderr).count("the bag has no messages on /stereo/color") == 1, proc.stderr
    assert any("map bound: max_blocks 10 is smaller" in line for line in stats["warnings"]), stats["warnings"]
    assert all(line in proc.stderr for line in stats["warnings"]), (stats["warnings"], proc.stderr)


def test_a_few_damaged_messages_among_good_ones_are_said_as_damaged_and_counted_in_the_frames(tmp_path: Path):
    """Three damaged depth images (empty, cut short, random bytes) among good ones: replay hinted at a bag of
    another kind ("ROS 1 or JSON data? convert the bag"), because one empty payload is no CDR, and said
    "tof: N of N frames fused", the damaged ones left out of the count."""
    import re

    rng = np.random.default_rng(1)
    damaged = {2: lambda data: b"", 4: lambda data: data[:len(data) // 2], 6: lambda data: rng.bytes(len(data))}
    recording = two()
    bag = with_damaged_messages(write_bag(recording, tmp_path / "plain"), tmp_path / "bag",
                                lambda topic, n, data: damaged[n](data) if topic == "/tof/depth" and n in damaged
                                else data)
    with open_bag(bag) as reader:
        in_bag = reader.topics["/tof/depth"].count
    proc = replay_in_process(bag, tmp_path / "out", params_file(tmp_path / "params.yaml", recording))
    assert proc.returncode == 0, proc.stderr
    assert re.search(rf"^tof: {in_bag - 3} of {in_bag} frames fused; 3 undecodable$", proc.stdout, re.M), proc.stdout
    assert f"3 of the {in_bag} message(s) on /tof/depth are damaged (could not be deserialised" in proc.stderr
    assert "ROS 1 or JSON" not in proc.stderr, proc.stderr
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["sensors"]["tof"]["undecodable"] == {"depth": 3} and stats["topics"]["/tof/depth"]["undecodable"] == 3
