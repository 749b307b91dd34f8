"""The pure core: geometry, frame conventions, MarkerData, fusion and the transform graph.

Imports nothing but numpy, scipy and the standard library; never reads a clock (time is passed in).
"""
