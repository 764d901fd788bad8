"""spiel-edge as a robot's service: systemd notify, watchdog and journald (``systemd``),
the unit/udev/sysusers kit (``kit``) and the installation checks (``doctor``)."""
