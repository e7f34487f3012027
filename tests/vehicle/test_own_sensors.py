"""Flying a vehicle on its own sensors (`cavenav fly` without --sim): the camera stream, a
monocular depth model, dead reckoning without a DVL, and the closed loop against fakes on
loopback (the simulated autopilot, an H.264 stream encoded on the fly, two Ping1Ds)."""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import socket
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cavenav.core.errors import ConfigError, VehicleError
from cavenav.core.types import Action, Observation, Pose
from cavenav.motion import kinematics
from cavenav.safety.shield import Shield
from cavenav.vehicle.camera import CameraAddress, FakeCamera, VideoCamera
from cavenav.vehicle.dead_reckoning import DeadReckoning
from cavenav.vehicle.fake_sub import FakeSub, FakeSubConfig
from cavenav.vehicle.mavlink import ArduSubMotion, BridgeConfig
from cavenav.vehicle.ping import FakePing1D
from cavenav.vehicle.ping360 import FakePing360
from cavenav.vehicle.waterlinked import DvlVelocity, FakeDvl
from tests.conftest import cavenav


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def free_rtp_port() -> int:
    """An even UDP port with the next one free too: RTP there, its RTCP on the next."""
    for _ in range(100):
        port = free_udp_port() & ~1
        with contextlib.ExitStack() as held:
            try:
                for each in (port, port + 1):
                    probe = held.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
                    probe.bind(("0.0.0.0", each))
            except OSError:
                continue
            return port
    raise AssertionError("no free pair of UDP ports")


def grey(level: int, size: tuple[int, int] = (320, 240)) -> np.ndarray:
    return np.full((size[1], size[0], 3), level, np.uint8)


# ---------------------------------------------------------------------------- the camera


@pytest.mark.parametrize(
    ("text", "kind", "where"),
    [
        ("udp:5600", "udp", "5600"),
        ("rtsp://192.168.2.2:8554/video_stream__dev_video2", "rtsp",
         "rtsp://192.168.2.2:8554/video_stream__dev_video2"),
        ("udp://0.0.0.0:5600", "url", "udp://0.0.0.0:5600"),
    ],
)  # fmt: skip
def test_a_camera_address_names_blueos_streams(text: str, kind: str, where: str) -> None:
    address = CameraAddress.parse(text)
    assert (address.kind, address.where, str(address)) == (kind, where, text)


@pytest.mark.parametrize("text", ["udp:", "udp:0", "udp:70000", "udp:port", " "])
def test_a_bad_camera_address_is_one_line(text: str) -> None:
    with pytest.raises(ConfigError, match="camera"):
        CameraAddress.parse(text)


@pytest.mark.slow
def test_the_camera_gives_the_first_frame_after_a_moment_at_the_pilots_size() -> None:
    levels = iter(range(10**6))
    shown: list[int] = []

    def frame(index: int) -> np.ndarray:
        shown.append(40 + (next(levels) * 10) % 200)
        return grey(shown[-1])

    with FakeCamera(frame, free_rtp_port()) as stream:
        address = CameraAddress.parse(stream.address)
        camera = VideoCamera(address, size=(160, 120), timeout_s=10, latency_s=1.0)
        try:
            moment = time.monotonic()
            sent_before = len(shown)  # streamed before the moment (and a second after it)
            image = camera.frame_after(moment)
            waited = time.monotonic() - moment
        finally:
            camera.close()
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8
    assert waited >= 1.0  # the latency given: nothing decoded sooner is taken
    # H.264 at ultrafast is lossy: the grey comes back within a few levels, and it is one
    # of the frames streamed at least half a second after the moment (a second's latency
    # given, less frames in flight), not one queued before it.
    level = int(np.median(image[..., 1]))
    later = shown[sent_before + 5 :]
    assert min(abs(level - sent) for sent in later) <= 4, (level, later[:5])


def test_a_wide_stream_is_cropped_to_the_pilots_aspect_not_squeezed() -> None:
    """A 16:9 stream given at 4:3: its sides go, so the pixels stay square, and the field
    of view given to the pilot is the part kept."""
    wide = np.zeros((180, 320, 3), np.uint8)
    wide[:, 40:280] = (0, 200, 0)  # the middle 4:3 of it green, the sides black

    with FakeCamera(lambda index: wide, free_rtp_port()) as stream:
        camera = VideoCamera(CameraAddress.parse(stream.address), size=(160, 120))
        try:
            image = camera.frame_after(time.monotonic())
            hfov = camera.hfov_deg(90.0)
        finally:
            camera.close()
    # Squeezed, a quarter of the frame would be the black sides; cropped, none is (but
    # for the codec's blur at the seams).
    assert (image[..., 1] > 100).mean() > 0.97
    assert hfov == pytest.approx(math.degrees(2 * math.atan(240 / 320)), abs=0.5)


def test_a_stream_that_never_comes_is_a_vehicle_error_naming_the_camera() -> None:
    port = free_rtp_port()
    started = time.monotonic()
    with pytest.raises(VehicleError, match=f"camera udp:{port}"):
        VideoCamera(CameraAddress.parse(f"udp:{port}"), timeout_s=1.0)
    assert time.monotonic() - started < 15


# ---------------------------------------------------------------------------- monocular depth


@pytest.fixture(scope="module")
def depth_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("transformers")
    from tests.tiny_depth import build_tiny_depth_anything

    return build_tiny_depth_anything(tmp_path_factory.mktemp("tiny-depth"))


def test_a_monocular_model_gives_metres_at_the_images_size(depth_model: Path) -> None:
    from cavenav.sensors.monocular import MonocularDepth

    estimate = MonocularDepth(depth_model, device="cpu")
    rgb = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    depth = estimate(rgb)
    assert depth.shape == (120, 160) and depth.dtype == np.float32
    assert np.all((depth > 0) & (depth <= 20))  # the head's metric range


def test_a_relative_depth_model_is_refused(tmp_path: Path) -> None:
    pytest.importorskip("transformers")
    from cavenav.sensors.monocular import MonocularDepth
    from tests.tiny_depth import build_tiny_depth_anything

    relative = build_tiny_depth_anything(tmp_path / "relative", kind="relative")
    with pytest.raises(ConfigError, match="relative depth"):
        MonocularDepth(relative)


def test_a_depth_model_that_does_not_say_it_gives_metres_is_refused(tmp_path: Path) -> None:
    """DPT's configuration has no kind: MiDaS (relative inverse depth) is a DPT."""
    pytest.importorskip("transformers")
    from transformers import DPTConfig

    from cavenav.sensors.monocular import MonocularDepth

    DPTConfig().save_pretrained(tmp_path)
    with pytest.raises(ConfigError, match=r"\(dpt\) does not say it predicts metres"):
        MonocularDepth(tmp_path)


def test_a_depth_model_must_be_a_local_folder(tmp_path: Path) -> None:
    from cavenav.sensors.monocular import MonocularDepth

    with pytest.raises(ConfigError, match="downloads nothing"):
        MonocularDepth("depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf")


# ---------------------------------------------------------------------------- dead reckoning


def test_reckoning_adds_moves_turned_by_the_measured_heading() -> None:
    east = math.radians(90)
    reckoned = DeadReckoning().moved(1.0, 0.0, east).moved(0.0, 0.5, east)
    assert reckoned.north == pytest.approx(-0.5) and reckoned.east == pytest.approx(1.0)


def test_the_calibration_error_grows_with_distance_and_the_compass_error_in_quadrature() -> None:
    reckoned = DeadReckoning(distance_error=0.1, heading_error_deg=3.0)
    for _ in range(10):
        reckoned = reckoned.moved(1.0, 0.0, 0.0)
    # 10 m: the calibration 0.1 x 10 m, the compass sqrt(10) x 1 m x 3 degrees.
    expected = math.hypot(1.0, math.sqrt(10) * math.radians(3.0))
    assert reckoned.sigma_m == pytest.approx(expected)
    assert DeadReckoning(heading_error_deg=0.0).moved(2.0, 0.0, 0.0).sigma_m == pytest.approx(0.2)


def udp_sub(position: bool, depth: float = 30.0) -> tuple[FakeSub, BridgeConfig]:
    """A fake sub at ``depth`` that does not rise while disarmed (neutrally buoyant), so
    that depths are reckoned from where it starts."""
    port = free_udp_port()
    sub = FakeSub(
        FakeSubConfig(
            address=f"udpout:127.0.0.1:{port}", start_ned=(0.0, 0.0, depth),
            position_estimate=position, buoyant_rise_mps=0.0,
        )
    )  # fmt: skip
    # still means still here (0.02 m/s in depth, not the SITL's 0.2, which allows for a
    # depth hold's waver): a frame taken after a move shows the depth the record says
    bridge = BridgeConfig(
        connect=f"udpin:127.0.0.1:{port}", connect_timeout_s=10.0, still_climb_mps=0.02
    )
    return sub, bridge


@pytest.mark.slow
def test_without_a_dvl_manual_mode_reckons_the_position_and_measures_depth_and_heading() -> None:
    from cavenav.core.types import Pose

    sub, bridge = udp_sub(position=False)
    motion = ArduSubMotion(bridge, reckon=True)
    with sub:
        try:
            start = motion.start(Pose(0.0, 0.0, 0.0, 0.0))
            assert motion.position == "reckoned" and motion.position_sigma_m == 0.0
            reached = motion.move(start, Action(forward=1.0, up=-0.5, yaw_deg=-90))
            truth = sub.state()
        finally:
            motion.close()
    # A right turn of 90 degrees, then 1 m forward: east, in the fake's north-east frame;
    # timed sticks with no DVL to close the loop, so the vehicle coasts on past the metre
    # (as ArduSub's SITL does) while the bridge waits for it to come still.
    assert truth.east == pytest.approx(1.1, abs=0.15) and abs(truth.north) < 0.15
    # Depth and heading as measured (the depth hold still settling, within centimetres);
    # the horizontal position as commanded.
    assert reached.z == pytest.approx(30.0 - truth.down, abs=0.05)
    assert math.degrees(reached.psi) == pytest.approx(-truth.yaw_deg, abs=1.0)
    assert math.hypot(reached.x, reached.y) == pytest.approx(1.0, abs=1e-6)
    assert motion.position_sigma_m == pytest.approx(math.hypot(0.1, math.radians(3.0)))


@pytest.mark.slow
def test_without_a_dvl_a_simulated_cave_or_guided_mode_is_refused() -> None:
    from cavenav.core.types import Pose

    sub, bridge = udp_sub(position=False)
    bridge = bridge.model_copy(update={"connect_timeout_s": 2.0, "position_timeout_s": 2.0})
    with sub:
        for motion in (ArduSubMotion(bridge), ArduSubMotion(
            bridge.model_copy(update={"mode": "guided"}), reckon=True)):  # fmt: skip
            try:
                refused = "LOCAL_POSITION_NED|refused MAV_CMD_DO_SET_MODE"
                with pytest.raises(VehicleError, match=refused):
                    motion.start(Pose(0.0, 0.0, 0.0, 0.0))
            finally:
                motion.close()


@pytest.mark.slow
def test_without_a_dvl_the_depth_is_the_bar30s_and_limits_never_add_a_move() -> None:
    """The depth from SCALED_PRESSURE2 (fresh water, standard air), kept for the flight;
    a vehicle floating above the shallowest depth allowed dives to it before the first
    step, and an ascent asked for there is cut to what is left above the limit (none
    once above it), never turned into a descent the shield never judged."""
    from cavenav.core.types import Pose

    sub, bridge = udp_sub(position=False, depth=0.17)
    limited = bridge.model_copy(update={"min_depth_m": 0.3, "start_depth_m": 0.3})
    motion = ArduSubMotion(limited, reckon=True)
    with sub:
        try:
            start = motion.start(Pose(0.0, 0.0, 0.0, 0.0))
            assert motion.depth_source == "SCALED_PRESSURE2"
            assert motion.start_report is not None
            before = motion.start_report["depth_m"]
            assert before == pytest.approx(0.3, abs=0.1)
            motion.move(start, Action(up=0.5))
            flown = motion.flown
        finally:
            motion.close()
    assert flown.up == pytest.approx(max(before - 0.3, 0.0), abs=0.011) and flown.up >= 0.0


def test_the_geometric_pilot_flies_with_a_sounder_that_reads_nothing_sure() -> None:
    """NaN (no sounder fitted, or one below its confidence) is unknown: never centred
    toward, never counted as the nearest surface, said as such."""
    from dataclasses import replace

    from cavenav.pilots.geometric import GeometricPilot
    from cavenav.sim.env import CaveNavEnv
    from cavenav.world.scenarios import load_scenario

    env = CaveNavEnv(load_scenario("S1", 0), resolution=(160, 120))
    _, info = env.reset(seed=0)
    for top, bottom in [(math.nan, 1.2), (1.2, math.nan), (math.nan, math.nan)]:
        observation = replace(info["observation"], d_top=top, d_bottom=bottom)
        decision = GeometricPilot().decide(observation)
        assert math.isfinite(decision.action.up)
        assert "unknown" in decision.justification
        verdict = Shield()
        verdict.observe(observation)
        verdict.judge(decision.action)  # judged, not raised


# ---------------------------------------------------------------------------- the shield


def test_without_a_depth_image_the_shield_lets_only_vertical_moves_fly() -> None:
    blind = Observation(
        rgb=np.zeros((120, 160, 3), np.uint8), depth_m=np.full((120, 160), np.nan, np.float32),
        depth_png=np.zeros((120, 160), np.uint8), d_top=1.5, d_bottom=2.5,
        depth_range=(0.0, 20.0), hfov_deg=53.13, has_depth=False,
    )  # fmt: skip
    shield = Shield()
    shield.observe(blind)
    assert shield.judge(Action(up=-1.0)).action == Action(up=-1.0)
    for move in (Action(forward=0.5), Action(right=0.2), Action(yaw_deg=15)):
        verdict = shield.judge(move)
        assert "no depth image" in verdict.reason
        assert not (verdict.action.forward or verdict.action.right or verdict.action.yaw_deg)


# ---------------------------------------------------------------------------- the closed loop


@pytest.mark.slow
def test_fly_without_a_simulator_flies_the_vehicles_own_sensors(
    tmp_path: Path, depth_model: Path
) -> None:
    """The geometric pilot on the tiny depth model, the fake sub with no DVL, a camera
    whose grey level shows the vehicle's true depth, 40 levels a metre, and two sounders
    that read the ceiling 1 m above and the floor 3 m below wherever the vehicle is: it
    descends on every step to centre itself, so a frame from before a move shows another
    depth than the one after it."""
    sub, bridge = udp_sub(position=False)

    def grey_of(depth: float) -> float:
        return 128 + 40 * (depth - 30.0)  # 30 m: 128; 3 m deeper at most: 248

    def true_depth_grey(index: int) -> np.ndarray:
        return grey(round(min(max(grey_of(sub.state().down), 0), 255)))

    def unlocked() -> DvlVelocity:  # a DVL with no bottom lock: the moves stay reckoned
        return DvlVelocity(
            time.time(), np.zeros(3), False, 0.0, -1.0, np.zeros(4), np.zeros(4, bool)
        )

    with (
        sub,
        FakeCamera(true_depth_grey, free_rtp_port()) as camera,
        FakePing1D(lambda: 1.0) as ceiling,
        FakePing1D(lambda: 3.0) as floor,
        FakePing360(lambda angle, samples, range_m: np.full(samples, 60, np.uint8)) as sonar,
        FakeDvl(unlocked) as dvl,
    ):
        # The fake camera encodes, and the flight decodes, on two cores shared with the
        # suite's other workers: light takes longer to become a decoded frame than the
        # 0.2 s a real camera needs (measured: a frame 0.06 m of descent stale under three
        # workers), so the flight is told the latency of this camera.
        result = cavenav(
            "fly", "--connect", bridge.connect, "--camera", camera.address,
            "--camera-latency", "0.5",
            "--ping-up", ceiling.address, "--ping-down", floor.address,
            "--depth-model", str(depth_model), "--steps", "3", "--yes",
            "--sonar", sonar.address, "--dvl", dvl.address, "--out", str(tmp_path),
        )  # fmt: skip
        truth, sonar_address = sub.state(), sonar.address
    assert result.returncode == 0, result.stderr
    (run_dir,) = tmp_path.iterdir()
    summary = json.loads((run_dir / "summary.json").read_text())
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    ending = (summary["status"], summary["termination"], summary["steps"])
    assert ending == ("finished", "budget", 3)
    assert summary["success"] is None and summary["position"] == "reckoned"
    assert summary["plots"] == {"topdown": "topdown.png", "side": "side.png"}
    assert all((run_dir / name).stat().st_size > 10_000 for name in summary["plots"].values())
    assert summary["vehicle"]["depth_image"] is True
    assert [(s["d_top_m"], s["d_bottom_m"]) for s in steps] == [(1.0, 3.0)] * 3
    # Each step's frame is the camera's after the move before it: its grey shows the
    # depth the record's pose says (the pose's z is -depth + 30 m). Each move descended
    # half a metre or more (20 grey levels), so a frame from before the move would show
    # the vehicle that much shallower. Within 0.2 m: after the move settles, ALT_HOLD
    # still pulls the vehicle back from its overshoot (a decimetre, measured, when the
    # frame comes 1.5 s after the move), and H.264 shifts a flat grey by a level or two.
    depths = [30.0 - step["pose"]["z"] for step in steps]
    assert all(later - earlier >= 0.5 for earlier, later in itertools.pairwise(depths))
    for step, depth in zip(steps, depths, strict=True):
        rgb = np.asarray(Image.open(run_dir / step["frames"]["rgb"]))
        assert abs(float(np.median(rgb[..., 1])) - grey_of(depth)) <= 8, step["step"]
        assert (run_dir / step["frames"]["depth_exr"]).is_file()
    flown = math.hypot(truth.north, truth.east)
    assert flown > 0.05  # forward too, though slowly: the ceiling is within the standoff
    # Reckoned from the moves commanded: without a DVL a move is timed sticks, and the
    # fake sub coasts on after them as ArduSub's SITL does (a 0.1 m push carries it about
    # 0.25 m), so the reckoning lags the truth by up to 0.15 m a step here.
    assert summary["progress_m"] == pytest.approx(flown, abs=0.2 + 0.2 * flown)
    assert summary["position_sigma_m"] > 0
    # The Ping360's disc and the DVL's readings ride along in every step.
    assert all(s["sonar"]["kind"] == "ping360" for s in steps)
    assert (run_dir / steps[-1]["frames"]["sonar_npz"]).is_file()
    assert steps[-1]["dvl"] == {
        "velocity_m_s": [None, None, None],
        "locked": False,
        "altitude_m": None,
        "sigma_m_s": 0.0,
    }
    assert summary["vehicle"]["sonar"] == sonar_address


@pytest.mark.slow
def test_a_fake_sub_in_a_cave_streams_its_camera_and_answers_as_its_sounders(
    tmp_path: Path,
) -> None:
    """`cavenav fake-sub --scene`: what the bridge reads is rendered at the true pose."""
    from cavenav.sensors.rig import SensorConfig
    from cavenav.sim.cave_sensors import CaveSensors
    from cavenav.vehicle.ping import PingSounders
    from cavenav.world.scenarios import load_scenario
    from tests.conftest import write_room

    room = load_scenario(str(write_room(tmp_path)), 0)  # 7 m high, the start halfway up
    sub, _ = udp_sub(position=False)
    sensors = SensorConfig().with_resolution(160, 120)
    pings = (free_udp_port(), free_udp_port())
    with sub, CaveSensors(sub, room, sensors, free_rtp_port(), pings) as cave:
        assert cave.pose() == room.start  # 2 m from the end wall behind it
        assert cave.clearance_m() == pytest.approx(2.0, abs=0.01)
        sounders = PingSounders.connect(cave.up.address, cave.down.address)
        camera = VideoCamera(CameraAddress.parse(f"udp:{cave.camera.port}"), (160, 120))
        try:
            d_top, d_bottom = sounders.read()
            streamed = camera.frame_after(time.monotonic())
        finally:
            sounders.close()
            camera.close()
    assert d_top == pytest.approx(3.5, abs=0.01) and d_bottom == pytest.approx(3.5, abs=0.01)
    from cavenav.sensors.rig import SensorRig
    from cavenav.world.raycast import RayCaster

    rendered = SensorRig(RayCaster(room.mesh), sensors).render(room.start).rgb
    assert abs(float(streamed.mean()) - float(rendered.mean())) < 3  # H.264, lossy


def test_a_cameras_password_is_never_shown_or_recorded() -> None:
    address = CameraAddress.parse("rtsp://pilot:hunter2@192.168.2.2:8554/video")
    assert address.where == "rtsp://pilot:hunter2@192.168.2.2:8554/video"  # what FFmpeg opens
    assert str(address) == "rtsp://pilot:[redacted]@192.168.2.2:8554/video"


class _StillCamera:
    def frame_after(self, moment: float) -> np.ndarray:
        return np.full((48, 64, 3), 90, np.uint8)


class _Sounders:
    def read(self) -> tuple[float, float]:
        return 1.5, 1.5


class _ObedientVehicle:
    """Flies every move exactly, and says where it is."""

    position, position_sigma_m, depth_source, flown = "reported", None, None, Action()

    def start(self, pose: Pose) -> Pose:
        return pose

    def move(self, pose: Pose, action: Action) -> Pose:
        self.flown = action
        return kinematics.apply(pose, action)


def test_ctrl_c_while_a_flights_plots_are_drawn_leaves_it_finished(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from cavenav.episode import plots
    from cavenav.episode.on_vehicle import Flight, VehicleSenses, fly_on_sensors
    from cavenav.episode.settings import EpisodeConfig
    from cavenav.pilots.geometric import GeometricPilot

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "plot_flight", interrupted)
    senses = VehicleSenses(_StillCamera(), _Sounders())
    flight = Flight(EpisodeConfig(max_steps=2, save_frames=False))
    with pytest.raises(KeyboardInterrupt):
        fly_on_sensors(GeometricPilot(), senses, _ObedientVehicle(), flight, tmp_path / "run")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert (summary["status"], summary["steps"]) == ("finished", 2)
    assert "plots" not in summary


def test_a_fake_sub_in_a_cave_answers_as_a_ping360_and_a_dvl(tmp_path: Path) -> None:
    """`cavenav fake-sub --scene --sonar-port --dvl-port`: the sonar's echoes and the
    DVL's reports are rendered at the true pose, and read as `fly --sonar --dvl` reads
    them."""
    from cavenav.episode.own_acoustics import DvlFeed, SweptSonar
    from cavenav.sensors.fusion import echo_ranges
    from cavenav.sensors.rig import SensorConfig
    from cavenav.sim.cave_sensors import CaveSensors
    from cavenav.vehicle.ping360 import Ping360Settings, Ping360Sonar
    from cavenav.vehicle.waterlinked import WaterLinkedDvl
    from cavenav.world.scenarios import load_scenario
    from tests.conftest import write_room

    room = load_scenario(str(write_room(tmp_path)), 0)  # an 8 m wide hall, 7 m high
    sub, _ = udp_sub(position=False)
    sensors = SensorConfig().with_resolution(160, 120)
    pings = (free_udp_port(), free_udp_port())
    ports = {"sonar_port": free_udp_port(), "dvl_port": 0}
    with sub, CaveSensors(sub, room, sensors, free_rtp_port(), pings, **ports) as cave:
        assert cave.sonar is not None and cave.dvl is not None
        settings = Ping360Settings(range_m=10.0, sector_deg=200.0, step_grad=10)
        sonar = SweptSonar(Ping360Sonar.connect(cave.sonar.address, settings))
        feed = DvlFeed(WaterLinkedDvl.connect(cave.dvl.address))
        try:
            deadline = time.monotonic() + 20

            image = sonar.image()
            # The beams square to the side walls, which the assertions read.
            right = int(np.argmin(np.abs(image.bearings_deg - 90.0)))
            left = int(np.argmin(np.abs(image.bearings_deg + 90.0)))
            # Until the head has swept both: where its sweep starts varies with the load.
            while not np.isfinite(image.age_s[[right, left]]).all():
                assert time.monotonic() < deadline, "the Ping360 did not sweep both walls"
                time.sleep(0.1)
                image = sonar.image()
            time.sleep(0.5)
            reading = feed.reading()
        finally:
            sonar.close()
            feed.close()
    ranges = echo_ranges(replace(image, age_s=np.zeros_like(image.age_s)))
    # The side walls are 4 m either side of the hall's axis.
    assert ranges[right] == pytest.approx(4.0, abs=0.3) and ranges[left] == pytest.approx(
        4.0, abs=0.3
    )
    assert image.fan.shape == (400, 400) and image.fan.any()
    assert reading is not None and reading.locked  # the floor 3.5 m below
    assert reading.velocity_m_s == pytest.approx(np.zeros(3), abs=0.05)  # the sub sits still
    assert reading.altitude_m == pytest.approx(3.5, abs=0.05)
