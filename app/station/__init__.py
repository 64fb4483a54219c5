"""The guided station: a session state machine (machine.py), auto-capture (autocapture.py), the
controller that drives a rig through a session (station.py) and the browser panel (panel.py)."""
