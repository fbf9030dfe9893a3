"""A four-wheeled skid-steer robot with spring-damper suspension on rough terrain (MuJoCo).

The setting of SIDM (Wang & Johnson): robots that differ in suspension stiffness, damping and
travel. Sim only (no driver, no emulator): learning/transfer/wheeled_pairs.py builds it with
``registry.make_backend("wheeled", "sim", ...)``.
"""
