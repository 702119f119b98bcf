"""The units ASTERIX counts in, in SI. Typed records hold SI (m, rad, s, m/s), degrees for
latitude and longitude, and flight levels as flight levels (hundreds of feet of pressure
altitude: a unit of its own, not a distance)."""

import math

NM = 1852.0  # m, exactly
FT = 0.3048  # m, exactly
KT = NM / 3600.0  # m/s
FT_PER_MIN = FT / 60.0  # m/s
TURN = 2.0 * math.pi  # rad
DAY = 86400.0  # s: a time of day counts from midnight UTC and wraps here
TOD_LSB = 1.0 / 128.0  # s, the time-of-day resolution of every category here
