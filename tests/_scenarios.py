"""A small scenario file written for a test: one static target seen by one sensor of each
kind (the emulators' and clutter tests' common ground)."""

from __future__ import annotations

import textwrap

from sensors_sim import load_scenario

N_SCANS = 10_000

# A static target at az ≈ 53.1°, el ≈ 16.7°, range ≈ 10.4 km from the origin.
TARGET = [8000.0, 6000.0, 3000.0]

SENSORS = """
    [sensors.df]
    kind = "df"
    pos_m = [0.0, 0.0, 0.0]
    period_s = 1.0
    std_az_rad = 0.0175

    [sensors.radar2d]
    kind = "radar2d"
    pos_m = [0.0, 0.0, 0.0]
    period_s = 1.0
    std_az_deg = 1.0
    std_range_m = 20.0

    [sensors.angle]
    kind = "angle"
    pos_m = [0.0, 0.0, 0.0]
    period_s = 1.0
    std_az_deg = 0.05
    std_el_deg = 0.05

    [sensors.radar3d]
    kind = "radar3d"
    pos_km = [1.0, -2.0, 0.1]
    period_s = 1.0
    start_s = 0.5
    std_az_deg = 1.0
    std_el_deg = 2.0
    std_range_km = 0.05
"""


# The origin and defaults every such file starts with.
HEADER = """\
[origin]
lat_deg = 21.0
lon_deg = 105.0
alt_m = 0.0
[defaults]
topology = "centralised"
method = "SS"
"""


def write_scenario(tmp_path, sensors: str = SENSORS, targets: str | None = None, duration=N_SCANS - 0.5,
                   seed=11, name="emu.toml"):
    targets = targets or f"""
        [targets.T1]
        pos_m = {TARGET}
        segments = [{{ type = "static" }}]
    """
    text = textwrap.dedent(f"""\
        description = "emulator test"
        seed = {seed}
        duration_s = {duration}
    """) + HEADER + textwrap.dedent(targets) + textwrap.dedent(sensors)
    path = tmp_path / name
    path.write_text(text)
    return load_scenario(path)
