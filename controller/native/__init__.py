"""The controller core in C99 (src/, include/rhonn_core.h), built at install into
``_rhcore64`` / ``_rhcore32``, and its Python side: configuration struct, binding wrapper,
backend choice, OSQP code generation and the microcontroller build."""
