"""Replaying a robot's recorded control steps (``stack-replay``): the log (:mod:`.log`), the replay and the
bit-for-bit comparison (:mod:`.run`), what a divergence leaves to look at (:mod:`.show`), the CLI (:mod:`.cli`)."""
