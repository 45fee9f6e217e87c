"""The test bench: runs plant and controller processes on a bus, analyses, reproduces the paper,
visualises.
"""
