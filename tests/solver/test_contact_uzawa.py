"""Augmented-Lagrangian bookkeeping: the bounded Uzawa loop."""
import numpy as np
import pytest

from solver.contact import SurfaceContact
from solver.contact._uzawa import UzawaLoop, deepest_penetration


def test_uzawa_loop_is_bounded_and_restarts_at_every_load():
    loop = UzawaLoop(max_augmentations=2, schedule="every_step")
    assert loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert not loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1)   # bounded
    assert loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1)       # new load
    assert not loop.another_solve(1.0, False, True, error=0.05, tolerance=0.1)  # converged


def test_carried_schedule_updates_intermediate_steps_without_a_resolve():
    # "carried": an intermediate load step whose penetration exceeds the tolerance is not
    # solved again but asks for a multiplier update (carry); a wrong status still re-solves;
    # the final load is augmented down to the tolerance as with "every_step"
    loop = UzawaLoop(max_augmentations=3)
    assert loop.schedule == "carried"
    assert not loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1) and loop.carry
    assert not loop.another_solve(0.5, False, True, error=0.05, tolerance=0.1) and not loop.carry
    assert loop.another_solve(0.75, True, True, error=0.05, tolerance=0.1)      # status
    assert not loop.another_solve(0.75, False, False, error=1.0, tolerance=0.1) and not loop.carry
    assert loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1) and not loop.carry
    assert not loop.another_solve(1.0, False, True, error=0.05, tolerance=0.1)
    final = UzawaLoop(max_augmentations=3, schedule="final_only")
    assert not final.another_solve(0.5, False, True, error=1.0, tolerance=0.1)
    assert not final.carry
    with pytest.raises(ValueError, match="schedule"):
        UzawaLoop(3, schedule="sometimes")


def test_carried_multipliers_follow_the_load_ratio():
    # the multipliers carried to a new load are scaled by new / previous load, at its first
    # evaluation only; a cut-back (a smaller load after a larger one) scales them back
    loop = UzawaLoop(3)
    assert loop.load_factor(0.25) == 1.0                     # nothing carried yet
    assert loop.load_factor(0.25) == 1.0
    assert loop.load_factor(0.5) == pytest.approx(2.0)
    assert loop.load_factor(0.5) == 1.0
    assert loop.load_factor(0.375) == pytest.approx(0.75)    # cut back from 0.5
    assert UzawaLoop(3, schedule="every_step").load_factor(0.25) == 1.0
    every = UzawaLoop(3, schedule="every_step")
    every.load_factor(0.25)
    assert every.load_factor(0.5) == 1.0


def test_a_rigid_contact_term_carries_its_multipliers_to_the_next_load():
    # A node 0.2 mm inside a plane (tolerance 0.05): at the intermediate load 0.5 the term
    # asks for no re-solve but takes the Uzawa update lambda = eps g A; at load 1 the first
    # evaluation doubles it, and the final load is augmented (re-solve asked)
    from solver.contact import RigidSurfaceContact

    V = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    nodes = np.array([[0.0, 0.0, -0.2]])
    term = RigidSurfaceContact(nodes, V, F, slave_nodes=[0], slave_areas=[1.0], penalty=10.0,
                               tolerance=0.05)
    term.assemble(nodes, 0.5)
    assert term.end_step(nodes, 0.5) is False
    assert term.multipliers[0] == pytest.approx(10.0 * 0.2)         # eps * depth * area
    term.assemble(nodes, 1.0)
    assert term.multipliers[0] == pytest.approx(2.0 * 10.0 * 0.2)
    assert term.end_step(nodes, 1.0) is True


def _bent_patch_contact():
    """A 2 x 2 slave quad 0.01 mm into a master patch that is flat for x < 2 and rises with
    slope 0.5 beyond (a crease at x = 2); the contact status frozen (5 evaluations)."""
    gx, gy = np.meshgrid(np.arange(4.0), np.arange(3.0), indexing="ij")
    bottom = np.stack([gx.ravel(), gy.ravel(), 0.5 * np.maximum(gx - 2.0, 0.0).ravel()], axis=1)
    quads = np.array([[i * 3 + j, (i + 1) * 3 + j, (i + 1) * 3 + j + 1, i * 3 + j + 1]
                      for i in range(3) for j in range(2)])                  # normal +z
    sx, sy = np.meshgrid([0.3, 1.3], [0.6, 1.6], indexing="ij")
    top = np.stack([sx.ravel(), sy.ravel(), np.full(4, -0.01)], axis=1)
    x = np.vstack([bottom, top])
    slave = np.array([[0, 1, 3, 2]]) + len(bottom)                           # normal -z
    term = SurfaceContact(x, slave, quads, two_pass=False, penalty=50.0, tolerance=0.05,
                          search_radius=1.0, max_depth=1.0, ignore_initial_penetration=False)
    for _ in range(5):
        term.assemble(x, 1.0)
    ps = term.passes[0]
    assert ps.active.all() and term._evals > term.freeze_after
    cen = x[ps.master].mean(axis=1)
    return term, ps, x, cen


def test_a_pairing_change_that_moves_no_force_asks_for_no_resolve():
    # The slave's frozen triangle is swapped for another one of the same plane: the forces
    # of the frozen and of a fresh search agree, the penetration (0.01) is within the
    # tolerance, so the step is accepted (a node over a flat patch's diagonals used to cycle)
    term, ps, x, cen = _bent_patch_contact()
    flat = np.nonzero(cen[:, 0] < 2.0)[0]
    ps.previous[0] = flat[flat != ps.previous[0]][0]
    assert term.end_step(x, 1.0) is False


def test_a_pairing_change_that_moves_the_force_asks_once_per_node_and_step():
    # The frozen triangle is on the inclined side: its plane is ~0.3 mm from the slave, the
    # fresh one 0.01 mm: the forces differ by more than the tolerance -> solve again; the same
    # disagreement at the same load a second time is accepted (no endless alternation); at a
    # new load the node may ask again
    term, ps, x, cen = _bent_patch_contact()
    inclined = np.nonzero(cen[:, 0] > 2.0)[0]
    ps.previous[0] = inclined[0]
    assert term.end_step(x, 1.0) is True
    for _ in range(5):
        term.assemble(x, 1.0)
    ps.previous[0] = inclined[0]
    assert term.end_step(x, 1.0) is False
    term2, ps2, x2, _ = _bent_patch_contact()
    ps2.previous[0] = inclined[0]
    assert term2.end_step(x2, 1.0) is True


def test_deepest_penetration_over_passes():
    assert deepest_penetration([np.array([0.2, -0.03]), np.zeros(0), np.array([-0.01])]) == 0.03
    assert deepest_penetration([np.array([0.2]), np.zeros(0)]) == 0.0     # separated: 0
    assert deepest_penetration([]) == 0.0


def test_a_resolve_re_decides_the_status_twice_then_freezes_it():
    # After `end_step` asks for another solve of the same load, the status is searched afresh
    # at the re-solve's first two evaluations (the converged state, then after the first
    # update) and frozen from the third (`freeze_resolves`); without it the whole
    # `freeze_after` free phase is spent again. Checked on the frozen flag both terms use.
    from solver.contact import RigidSurfaceContact

    for resolves, free in ((True, 2), (False, 4)):
        term, ps, x, cen = _bent_patch_contact()
        term.freeze_resolves = resolves
        ps.previous[0] = np.nonzero(cen[:, 0] > 2.0)[0][0]
        assert term.end_step(x, 1.0) is True
        frozen = [term._frozen(1.0) for _ in range(free + 2)]
        assert frozen == [False] * free + [True, True]
    # the rigid term: a node 0.2 mm inside a plane, tolerance 0.05 -> augmented re-solve
    V = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    nodes = np.array([[0.0, 0.0, -0.2]])
    for resolves, free in ((True, 2), (False, 4)):
        rigid = RigidSurfaceContact(nodes, V, F, slave_nodes=[0], slave_areas=[1.0],
                                    penalty=10.0, tolerance=0.05, freeze_resolves=resolves)
        for _ in range(5):
            rigid.assemble(nodes, 1.0)
        assert rigid.end_step(nodes, 1.0) is True
        frozen = [rigid._frozen(1.0) for _ in range(free + 2)]
        assert frozen == [False] * free + [True, True]


@pytest.mark.parametrize("kind", ["surface", "segment", "segment_nodal"])
def test_deformable_terms_scale_their_carried_multipliers_with_the_load(kind):
    # The carried multipliers of both passes (and the nodal field of mortar-like multipliers)
    # follow the load ratio at a new load's first evaluation: x1.5 from 0.5 to 0.75, and a
    # cut-back to 0.625 scales them by 0.625 / 0.75; further evaluations at the same load
    # leave them alone. With "every_step" they are never scaled.
    from solver.contact import SegmentContact
    from tests.solver.test_contact_segment import _wavy_patches

    x, a, b = _wavy_patches()
    for schedule, factors in (("carried", (1.5, 1.5, 1.25)), ("every_step", (1.0, 1.0, 1.0))):
        if kind == "surface":
            term = SurfaceContact(x, a, b, penalty=50.0, search_radius=1.0,
                                  uzawa_schedule=schedule)
        else:
            term = SegmentContact(x, a, b, penalty=50.0, search_radius=1.0,
                                  nodal_multipliers=kind == "segment_nodal",
                                  uzawa_schedule=schedule)
        term.assemble(x, 0.5)
        arrays = lambda: [ps.multipliers for ps in term.passes] + (
            [ps.node_multipliers for ps in term.passes] if kind == "segment_nodal" else [])
        for ps in term.passes:
            ps.multipliers = np.linspace(1.0, 2.0, len(ps.multipliers))
            if kind == "segment_nodal":
                ps.node_multipliers = np.linspace(1.0, 2.0, len(ps.node_multipliers))
        before = [m.copy() for m in arrays()]
        for load, scale in zip((0.75, 0.75, 0.625), factors):     # scale: from load 0.5
            term.assemble(x, load)
            for m0, m in zip(before, arrays()):
                assert np.allclose(m, scale * m0, rtol=1e-12)


def test_update_flag_is_set_for_a_resolve_or_a_carried_update_with_augmentation_only():
    # `update` tells a term to set its multipliers to <lambda - eps g>: on a re-solve when
    # augmented (not for a status-only re-solve of a pure penalty term), and on a carried step
    loop = UzawaLoop(max_augmentations=3)
    assert not loop.another_solve(0.5, False, True, error=1.0, tolerance=0.1) and loop.update
    assert not loop.another_solve(0.5, False, True, error=0.05, tolerance=0.1)
    assert not loop.update
    assert loop.another_solve(0.75, True, False, error=0.05, tolerance=0.1) and not loop.update
    # a status re-solve of an intermediate step keeps the multipliers even when augmented:
    # its intermediate penetration does not matter, and an update would be one more jump of
    # the contact forces per re-solve
    assert loop.another_solve(0.8, True, True, error=1.0, tolerance=0.1) and not loop.update
    assert loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1) and loop.update
    assert loop.another_solve(1.0, True, True, error=1.0, tolerance=0.1) and loop.update


def test_an_intermediate_step_is_re_solved_for_its_status_a_bounded_number_of_times():
    # with status_resolves=1 the second status change of an intermediate step is accepted
    # (the next load searches the status afresh), with a carried update if it penetrates;
    # the final load is re-solved for every status change up to max_augmentations
    loop = UzawaLoop(max_augmentations=5, status_resolves=1)
    assert loop.another_solve(0.5, True, True, error=1.0, tolerance=0.1)
    assert not loop.another_solve(0.5, True, True, error=1.0, tolerance=0.1) and loop.carry
    assert loop.another_solve(0.75, True, True, error=0.05, tolerance=0.1)     # a new step
    for _ in range(5):
        assert loop.another_solve(1.0, True, True, error=0.05, tolerance=0.1)
    assert not loop.another_solve(1.0, True, True, error=0.05, tolerance=0.1)  # bounded
    unbounded = UzawaLoop(max_augmentations=5)
    for _ in range(5):
        assert unbounded.another_solve(0.5, True, True, error=1.0, tolerance=0.1)


def test_a_carried_correction_is_applied_in_proportion_to_the_next_step():
    # A node 0.2 mm inside a plane: the step 0.25 -> 0.5 takes the carried update
    # lambda = eps g A = 2; at the next load the correction (2 - 0) is applied in the
    # proportion of the next increment to 0.25 (rule 2), then scaled by the load ratio
    from solver.contact import RigidSurfaceContact

    V = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    nodes = np.array([[0.0, 0.0, -0.2]])
    term = RigidSurfaceContact(nodes, V, F, slave_nodes=[0], slave_areas=[1.0], penalty=10.0,
                               tolerance=0.05)
    term.assemble(nodes, 0.25)
    term.end_step(nodes, 0.25)               # the first carried update, from 0: lambda = 2
    term.assemble(nodes, 0.5)                # a full step: the whole correction, x 2
    assert term.multipliers[0] == pytest.approx(4.0)
    assert term.end_step(nodes, 0.5) is False
    assert term.multipliers[0] == pytest.approx(6.0)    # <lambda - eps g> = 4 + 2
    state = term.save_step()
    for dt, beta in ((0.25, 1.0), (0.0625, 0.25)):     # a full step, a quarter step
        term.restore_step(state)
        term.assemble(nodes, 0.5 + dt)
        expected = (4.0 + beta * 2.0) * (0.5 + dt) / 0.5
        assert term.multipliers[0] == pytest.approx(expected)


def test_augmentation_is_due_only_on_an_augmented_step_beyond_the_margin():
    # a step that is augmented down to the tolerance (the final one with "carried") and
    # penetrates beyond 1.5 tolerances will be augmented anyway; an intermediate step of
    # "carried" is not re-solved, nor a step of a penalty-only term, nor one whose count is
    # spent
    loop = UzawaLoop(max_augmentations=1)
    assert loop.augmentation_due(1.0, True, error=0.2, tolerance=0.1)
    assert not loop.augmentation_due(1.0, True, error=0.14, tolerance=0.1)
    assert not loop.augmentation_due(0.5, True, error=1.0, tolerance=0.1)
    assert not loop.augmentation_due(1.0, False, error=1.0, tolerance=0.1)
    assert loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1)   # count 1 of 1
    assert not loop.augmentation_due(1.0, True, error=1.0, tolerance=0.1)
    every = UzawaLoop(max_augmentations=3, schedule="every_step")
    assert every.augmentation_due(0.5, True, error=0.2, tolerance=0.1)


@pytest.mark.parametrize("kind", ["rigid", "surface"])
def test_asking_whether_augmentation_is_due_leaves_the_contact_status_alone(kind):
    # `augmentation_due` evaluates the penetration at an iterate inside a solve: the status
    # the solve works with (active set, pairing, frozen or not) must not change
    from solver.contact import RigidSurfaceContact

    V = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    if kind == "rigid":
        nodes = np.array([[0.0, 0.0, -0.2], [1.0, 0.0, 0.3]])
        term = RigidSurfaceContact(nodes, V, F, slave_nodes=[0, 1], tolerance=0.05,
                                   search_radius=1.0)
        state = lambda: [(term._active.copy(), term._face.copy())]      # noqa: E731
    else:
        lower = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
        upper = lower + [0.0, 0.0, -0.2]                # 0.2 mm through the lower quad
        nodes = np.vstack([lower, upper])
        term = SurfaceContact(nodes, [[0, 1, 2, 3]], [[7, 6, 5, 4]], search_radius=1.0,
                              ignore_initial_penetration=False, tolerance=0.05)
        state = lambda: [(ps.previous.copy(), ps.active.copy()) for ps in term.passes]  # noqa
    term.assemble(nodes, 1.0)
    before = state()
    moved = nodes.copy()
    moved[:, 2] += np.where(nodes[:, 2] < 0, 0.5, 0.0)          # out of contact
    assert term.augmentation_due(nodes, 1.0)                    # 0.2 mm > 1.5 x 0.05
    assert not term.augmentation_due(moved, 1.0)
    for old, new in zip(before, state()):
        assert all(np.array_equal(p, q) for p, q in zip(old, new))


def test_carried_penalty_schedule_treats_the_final_load_as_an_intermediate_one():
    # "carried_penalty" (the face's fallback): no re-solve at any load for the penetration,
    # the multipliers carried (and scaled with the load) as "carried" does; one re-solve for a
    # wrong status, then the state is accepted; no early stop for an augmentation at load 1
    loop = UzawaLoop(max_augmentations=3, schedule="carried_penalty", status_resolves=1)
    assert not loop.another_solve(1.0, False, True, error=1.0, tolerance=0.1) and loop.carry
    assert loop.another_solve(1.0, True, True, error=1.0, tolerance=0.1) and not loop.update
    assert not loop.another_solve(1.0, True, True, error=1.0, tolerance=0.1)
    assert not loop.augmentation_due(1.0, True, error=1.0, tolerance=0.1)
    assert loop.load_factor(0.5) == 1.0 and loop.load_factor(1.0) == pytest.approx(2.0)
    # the default schedule augments the final load
    assert UzawaLoop(3).augmentation_due(1.0, True, error=1.0, tolerance=0.1)
