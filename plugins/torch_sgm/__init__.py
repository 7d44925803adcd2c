"""Stereo backend ``torch_sgm``: a classical matcher (cost, aggregation, SGM, WTA, refinement) in PyTorch.

Every stage is a pure tensor function so it runs unchanged on CPU and CUDA.
"""
