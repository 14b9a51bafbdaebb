"""The agent process (loop, decision layer, wiring): the only room that knows all the others."""
