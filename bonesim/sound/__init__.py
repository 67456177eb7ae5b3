"""Sound: the drill's data-driven sound (:mod:`~bonesim.sound.drill`) and the
nerve monitor's clicks (:mod:`~bonesim.sound.clicks`), synthesised as sample
blocks; the audio process that plays them is :mod:`bonesim.runtime.audio`.
Beside the physics in the layers: it imports nothing above the engine.
"""
