"""CAN transport: the python-can bus factory, the local Unix-socket bus and its hub, the
loopback bus server. Depends on :mod:`can_db.process` only, never on the CAN layer above it."""
