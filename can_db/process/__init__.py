"""Process plumbing the plant, controller and harness share and that is not CAN: argument
checks, CPU pinning, real-time set-up, stall detection, stop flags, crash-safe row logs, parent
death. Depends on nothing else in the project."""
