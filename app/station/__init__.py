"""The guided station: a session state machine (machine.py), auto-capture (autocapture.py), the
controller that drives a rig through a session (station.py), the browser panel (panel.py) and who may
use it (access.py: Origin, access code, throttle; _origin.py: its hook into viser's server)."""
