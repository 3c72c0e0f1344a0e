"""One simulation: a scene parsed from its files, made into cars of a world and stepped
by the compiled core; headless scenarios with their keyframed inputs, and the soak."""
