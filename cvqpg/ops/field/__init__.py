"""The SLM field and clamped intensity kernels."""
