"""The controller core in C99 (src/, include/rhonn_core.h), built at install into
``_rhcore64`` / ``_rhcore32`` with a cffi binding generated from the headers (cdef_gen.py),
and its Python side: configuration filler, controller wrapper,
backend choice, OSQP code generation and the microcontroller build."""
