"""The stereo camera tracker behind the driver contract: a sensor (empty action space).

``config.py`` (params, spec), ``pipeline.py`` (frames → tracker → observation, shared by
every backend), ``uvc.py`` (two UVC streams through OpenCV, paired by timestamp),
``driver.py`` (the real backend). The sim backend renders the MuJoCo hand scene
(``sim_backends/shadow_hand/cameras.py: StereoCameraSim``).
"""
