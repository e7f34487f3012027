"""Start ArduSub's software-in-the-loop build (SITL), the real autopilot with its own
vehicle physics, to fly `cavenav fly` against (benchmarks/ardusub_sitl.py, the SITL test).

cavenav does not ship the binary (ArduPilot is GPLv3; build it as
docs/tutorials/fly-a-bluerov2.md says): ``CAVENAV_ARDUSUB`` names it, or the folder that
holds it beside ArduPilot's ``sub.parm``. Each instance ``n`` listens on TCP
5760 + 10 n (its SERIAL0), as ``sim_vehicle.py -I n`` would, and starts afresh: a wiped
EEPROM, the vehicle floating at the surface, disarmed in MANUAL.
"""

from __future__ import annotations

import os
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cavenav.core.errors import ConfigError, VehicleError

__all__ = ["ARDUSUB_ENV", "ardusub_binary", "ardusub_sitl"]

ARDUSUB_ENV = "CAVENAV_ARDUSUB"
HOME = "33.810313,-118.393867,0,185"  # ArduSub's autotest home: lat, lon, alt, heading
BOOT_TIMEOUT_S = 30.0


def ardusub_binary() -> Path | None:
    """The SITL binary ``CAVENAV_ARDUSUB`` names (the file, or its folder); None unset.

    Raises:
        ConfigError: it is set to no executable ardusub.
    """
    named = os.environ.get(ARDUSUB_ENV)
    if not named:
        return None
    path = Path(named)
    binary = path / "ardusub" if path.is_dir() else path
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        raise ConfigError(f"{ARDUSUB_ENV}={named}: no executable ardusub there")
    return binary


@contextmanager
def ardusub_sitl(binary: Path, instance: int, workdir: Path) -> Iterator[str]:
    """Run the SITL ``binary`` as instance ``instance`` in ``workdir`` (its EEPROM, logs and
    output, sitl.out); yield the address to connect to, and stop it afterwards. It stops
    too when this process dies: the SITL checks its parent every step.

    Raises:
        VehicleError: it did not open its port within 30 s (see sitl.out).
    """
    defaults = binary.parent / "sub.parm"
    command = [
        str(binary), "-S", "-w", "--model", "vectored", "--speedup", "1", "--slave", "0",
        *(["--defaults", str(defaults)] if defaults.is_file() else []),
        "--sim-address=127.0.0.1", f"-I{instance}", "--home", HOME, "--serial0", "tcp:0",
    ]  # fmt: skip
    workdir.mkdir(parents=True, exist_ok=True)
    with open(workdir / "sitl.out", "wb") as output:
        process = subprocess.Popen(command, cwd=workdir, stdout=output, stderr=subprocess.STDOUT)
    try:
        port = 5760 + 10 * instance
        _wait_for_port(port + 3, process, workdir)  # SERIAL2: SERIAL0 takes one client
        yield f"tcp:127.0.0.1:{port}"
    finally:
        process.terminate()
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _wait_for_port(port: int, process: subprocess.Popen[bytes], workdir: Path) -> None:
    deadline = time.monotonic() + BOOT_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise VehicleError(f"the ArduSub SITL exited ({process.returncode}): see "
                               f"{workdir / 'sitl.out'}")  # fmt: skip
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise VehicleError(f"the ArduSub SITL opened no TCP port {port} in {BOOT_TIMEOUT_S:g} s")
