"""Every target a bone shell is held to, in one place: the verdict, the benchmarks and the tests read
them here.  A shell ships ``ok`` when it is closed and manifold, does not cross itself, and lies
within these distances of its label's boundary."""

#: The shell's mean distance to its label's boundary, mm ...
MAX_MEAN_DISTANCE_MM = 0.3
#: ... and its 95th percentile, mm.
MAX_P95_DISTANCE_MM = 0.8
