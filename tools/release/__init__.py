"""Release checks: wheels, other Pythons and architectures, fuzzing, the shipped models' verification."""
