"""The sensing pipeline (the seed's section III): raw captures to aligned samples, C2, sensor-level analyses.

=================  ==========================================================================================
module             what it does
=================  ==========================================================================================
``radiometry``     DJI M3T R-JPEG decoding (APP3 raw14, APP4 parameters, APP5 correction), decoded files + sidecars
``dji_correction`` DJI Thermal SDK correction of iirp temperatures (emissivity, reflection, APP5 tau table)
``dji_dirp``       DJI dirp (Zenmuse H20T) R-JPEGs: calibration block and curve to temperatures
``dji_formats``    which DJI R-JPEG layout a file uses (by EXIF model and APP4 tag); refusals naming both
``calibration``    checkerboard calibration per sensor, ``CameraModel`` YAML, undistortion without black borders
``registration``   (package) RGB->thermal homographies: their maths and focal priors, landmark fits, automatic
                   registration (ECC on edges), files, groups, a raw dataset's per-group policy, truth
``warp``           RGB warped into the thermal frame, common support, boxes carried through H, ``align_pair``
``c2``             the signed local radiometric contrast channel C2
``analyses``       registration error on landmarks, displacement study of C2 around boxes
``options``        the ``sensing:`` config section as typed records
``pipeline``       ``SensingContext``: one capture through undistortion, registration and alignment; the ir8 preview
=================  ==========================================================================================

Every function is a small, pure array-in/array-out step; the CLI (``harness sensing ...``) and the dataset
adapters compose them. Heavy imports (OpenCV) happen inside functions.
"""
