"""Exports of a calibration for the software that uses it (docs/FORMATS.md, "Exports"). One module per
target, each with one entry function `write(result, paths, options) -> warnings`:

  registry  EXPORTERS {name: Exporter(file names, writer)}, the defaults `procam calibrate` writes,
            `write_exports`, the trust gate of `procam export`
  common    what the exporters share: options, the devices and their poses, the residual (px) of a
            distortion a target cannot represent
  opencv    OpenCV FileStorage YAML (calibration.yaml)
  ros       ROS camera_info YAML, one per device
  mrcal     mrcal .cameramodel, one per device
  opengl    OpenGL projection and view matrices (column-major)
  engine    a physical camera per device for a game engine (unity, threejs)

Nothing is re-exported.
"""
