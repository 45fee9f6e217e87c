"""Running closed loops: the runner, process supervision, bus recorder, replay, in-process loop,
flood.
"""
