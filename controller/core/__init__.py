"""Pure controller core: models, learning, references, MPC, allocation. No I/O, no clock; never
imports ``controller.runtime``.
"""
