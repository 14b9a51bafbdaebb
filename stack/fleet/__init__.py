"""The fleet orchestrator: router, world and agents of a simulated run; report, plots, bench."""
