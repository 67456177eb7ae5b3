"""Bone dust and irrigation water on a sparse Eulerian grid over the bone.

:mod:`~bonesim.physics.dust.grid` holds :class:`~bonesim.physics.dust.grid.DustGrid`,
the state and its step; the kernels and tables it uses are in the sibling
modules (:mod:`~bonesim.physics.dust.bricks`: the brick layout and its
fixed-point units; :mod:`~bonesim.physics.dust.rules`: one step's moves;
:mod:`~bonesim.physics.dust.water`: irrigation; :mod:`~bonesim.physics.dust.sprites`:
what is drawn; :mod:`~bonesim.physics.dust.bodies`: cells of moved bone bodies;
:mod:`~bonesim.physics.dust.params`: the parameters from ``render.toml``).
Names are imported from the module that defines them.
"""
