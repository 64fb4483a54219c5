"""What the simulated rigs whose camera is a real driver share (drivers/sim/stream.py's SimUvcRig,
drivers/sim/realsense_bridge.py's SimRealSenseRig): everything but the camera comes from the wrapped
simulated rig (`sim`), and closing stops the driver, then whatever feeds it, then the simulated rig."""

from __future__ import annotations


class SimDriverRig:
    """Base of a simulated rig whose `camera` is a driver reading the simulated camera (`sim`)."""

    def __getattr__(self, name):  # scenario, projector, operator, ground_truth, renderer, ...
        return getattr(self.sim, name)

    def _close_feed(self) -> None:
        """Close what carries the simulated camera's frames to the driver (nothing by default)."""

    def close(self) -> None:
        try:
            self.camera.stop()
        finally:
            try:
                self._close_feed()
            finally:
                self.sim.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
