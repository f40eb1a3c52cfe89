"""Grid data: file formats (``.vol``, ``.npy``, ``.vdb``), the checks every reader
shares, where a medium's values live (dense textures, sparse bricks, nested volumes),
their cell bounds, placement in the scene, RGB in spectral and mono variants, and the
blackbody spectra of fire. Nothing here knows about tracking or integrators."""
