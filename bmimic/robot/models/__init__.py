"""The built-in robots, one module each, found by name (`bmimic.robot.registry`).

A robot module holds the robot's body and nothing else: `ROBOT`, a `bmimic.robot.spec.RobotModel`
(its hinge joints in model order, its solver options, a builder of its MjSpec). Its numbers (motor
classes, PD design, default pose, tracked bodies) live in conf/robot/<name>.yaml only. A second robot is
models/<name>.py plus conf/robot/<name>.yaml; no other file changes.
"""
