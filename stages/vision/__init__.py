"""Calibration, segmentation and video input (OpenCV, pycolmap).

- geometry.py      rigid poses, OpenCV projection with distortion, Umeyama, triangulation
- boards.py        board specs, corner detection, board textures and renders, board_poses.json format
- calibration.py   intrinsics per camera, extrinsics chained through shared views + joint refinement
- sfm.py           pycolmap structure from motion, scale from a board or a known distance
- colmap_io.py     COLMAP text/binary cameras+images and nerfstudio transforms.json (read and write)
- segmentation.py  background difference with shadows, chroma key, mesh-seeded GrabCut, clean-up
- sam2_model.py    optional SAM 2 segmenter behind an import check
"""
