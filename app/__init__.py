"""procam-station application layer: the command line, the guided session and the viser panel."""
