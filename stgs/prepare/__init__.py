"""`stgs prepare`: one video per camera in, a synchronised, calibrated capture out (docs/CAPTURE.md, "Preparing
raw footage").

The stages, in order: check the footage (footage), synchronise it (sync), calibrate the rig on a few frames
(calibrate), then write every frame of the common span undistorted in one of the readers' layouts (output);
`run.prepare` drives them and writes `prepare_report.json`. `settings` holds the choices and defaults, light
enough for the command line's parser.
"""
