"""Release tools: wheels with prebuilt kernels (``build_wheels``), the wheel check of the
dependencies (``check_wheels``), the emulated aarch64 root (``aarch64_smoke.sh``), other
Pythons, fuzzing, and the shipped models' verification."""
