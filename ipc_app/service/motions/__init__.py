"""The service's motions (:class:`~ipc_app.service.motion.Motion`), one module each:
an adapter over its :mod:`ipc_app.control` sequencer.

=============  ==========================================================================
module         motion
=============  ==========================================================================
attitude       ``adjust`` (the planner's trajectory; its hand-off from the planner
               process), ``jog`` (one cylinder, MANUAL); the base of the layer motions
walk           ``walk``: :class:`~ipc_app.control.walk.WalkSequencer`
place          ``place``: :class:`~ipc_app.control.placement.PlacementSequencer`
release        ``release``: :class:`~ipc_app.control.release.ReleaseSequencer`
homing         ``home``: each attitude layer to mid-stroke, level
=============  ==========================================================================
"""
