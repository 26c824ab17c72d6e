"""The simulator: robots from URDF, controllers, occupancy/collisions, the step loop, Gymnasium envs.

Entry points: :class:`presim.sim.simulator.Simulator`, :func:`presim.sim.robot.load_robot`,
``presim.sim.envs`` (importing it registers ``PreSim-PointNav-v0`` with gymnasium). See docs/simulator.md. Nothing heavy is
imported here: sinks import :mod:`presim.sim.types` alone.
"""
