"""LIBERO, the paper's second benchmark, read from the installed LIBERO package (docs/libero.md).

    from envs.libero import scene, suites, predicates
    tasks = suites.tasks("libero_object")            # names, BDDL files, instructions
    s = scene.scene("libero_object", 0)               # the composed MJCF, cached on disk
    model = scene.model(s); data = mujoco.MjData(model)
    scene.set_init_state(model, data, suites.init_states("libero_object", 0)[3])
    goal = predicates.compile_goal(s, model); predicates.satisfied(goal, predicates.state_of(goal, data))

    from envs.libero import engine                    # B copies on MuJoCo's C engine, LIBERO's actions
    batch = engine.LiberoBatch(s, 50); batch.reset(suites.init_states("libero_object", 0))
    batch.step(actions)                                # [50, 7]: OSC_POSE deltas + gripper
    batch.success()                                    # [50] bool, as LIBERO's _check_success

Nothing here is imported by `envs` itself, and LIBERO is imported only inside the functions that
need it: importing `envs` or `envs.libero` loads neither LIBERO nor robosuite.
"""
