"""The tire-model registry: each model's id, parameter loader and compiled kernels."""
