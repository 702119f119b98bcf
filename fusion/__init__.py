"""zfusion estimation library.

Pure numerics: numpy/scipy only, no I/O, no clocks, no Zenoh. The services and the
Monte Carlo harness call the very same functions, so a distributed run and an
in-process evaluation of one scenario give the same numbers.
"""
