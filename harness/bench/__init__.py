"""``rhonn-bench``: benchmarks of the codec, bus, plant, controller, closed loop and soak."""
