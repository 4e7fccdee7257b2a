"""Band construction, FastFPS orchestration, and the Euclidean tail and baseline."""
