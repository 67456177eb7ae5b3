"""Files in and out: cases and their volumes (DICOM, NRRD, NIfTI, label stacks,
segmentations), anatomy, the phantom, burrs, meshes, trajectories and tool
paths, and building a Model from them.
"""

__all__: list[str] = []
