"""Task definitions, apart from robots and planners (as mujoco_mpc keeps each task apart).

The ground floor beside ``configs``: a task here depends on configs, numpy and pydantic only,
so a sim backend, an emulator, a cost in control/ and an experiment in learning/ all use the
same definition without importing one another or a robot package.

* :mod:`.baoding`: the Baoding task (targets, reward, drop, target phase; PDDM).
* :mod:`.perturbations`: the conditions the adaptation experiments put a VelociRoACH in.
"""
