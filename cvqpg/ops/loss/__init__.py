"""The training loss kernels."""
