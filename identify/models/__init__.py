"""Fitted models: the Koopman model and its batched prediction, per-episode offsets in
prediction, and model files (MODEL_FORMAT.md).
"""
