"""SAPIEN simulation of the Girona AUV, its docking station and the underwater camera.

Modules:
    vehicle:         vehicle parameters, randomisation, Fossen hydrodynamics, ocean current,
                     IMU (world NED / body FRD; the acceleration kernel is numba-compiled).
    thrusters:       thruster geometry, allocation with uniform saturation, thrust curve, lag.
    fastpath:        numba kernels: the hydrodynamic acceleration, PhysX's integration step for
                     free flight, static obstacle boxes.
    physics:         the vehicle as a SAPIEN/PhysX rigid body at 300 Hz (the only place where
                     the marine frames meet SAPIEN's z-up world and FLU actors); free flight
                     skips PhysX when no contact is possible.
    batch:           N vehicles stepped as arrays in one process (``BatchVehicles``, the batched
                     training simulator), PhysX only for DS contact.
    contact_scene:   one PhysX scene for the DS contact of all of a batch's vehicles (a twin
                     body each, copies of their statics side by side): one step for all.
    docking_station: DS (guides, notches, 3D markers) and tank geometry.
    render:          the headless SAPIEN camera rig and ground-truth marker projection.
    camera:          THE simulated camera: ``SimCamera.capture`` = render + water, returning a
                     ``Frame`` that names its channel order (``img_rgb``, ``img_bgr()``).
    world_config:    ``WorldConfig`` of the world (SAPIEN-free; the env's ``EnvConfig.world``).
    world:           THE world of one docking env (scene, tank, DS, vehicle, currents, camera),
                     composed once.
    water:           underwater image formation (attenuation, backscatter, blur, noise, JPEG).
    usbl:            the acoustic (USBL) positioning of the DS: noise, per-episode bias,
                     outliers, dropouts and latency, with presets from published systems.
    navigation:      the vehicle's own navigation (DVL, AHRS, depth dead reckoning) as errors
                     on the true motion, for N vehicles at once, with a published-sensor preset.
    episode:         a video of a docking episode (``sim episode``).
    domains:         value domains shared by these modules' configs (``dockcore.domains``).
"""

if __name__ != "uwdock.sim":  # this folder reached as a top-level name (the working directory)
    raise ImportError(
        "this folder is installed as uwdock.sim: import uwdock.sim "
        "(pip install -e . from the repository puts it there)"
    )
