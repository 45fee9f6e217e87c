"""Offline tools (fitting the controller's MF tyre to the plant tyre)."""
