import numpy as np
import pytest

from lmpromp_ppl.basis import (
    block_basis,
    design_matrix,
    rbf_basis,
    rbf_basis_derivative,
    velocity_design_matrix,
)


def test_position_basis_rows_sum_to_one_at_irregular_phases():
    rng = np.random.default_rng(0)
    phase = np.sort(rng.uniform(-0.2, 1.2, size=37))
    phi = np.asarray(rbf_basis(phase, 9))
    assert phi.shape == (37, 9)
    np.testing.assert_allclose(phi.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.all(phi > 0)


def test_basis_peaks_at_centres():
    phi = np.asarray(rbf_basis(np.linspace(0, 1, 6), 6))
    assert np.all(np.argmax(phi, axis=1) == np.arange(6))


def test_block_structure_and_row_ordering():
    phase = np.linspace(0, 1, 5)
    num_dofs, num_basis = 3, 4
    psi = np.asarray(design_matrix(phase, num_dofs, num_basis))
    phi = np.asarray(rbf_basis(phase, num_basis))
    assert psi.shape == (5 * num_dofs, num_dofs * num_basis)
    for t in range(5):
        for k in range(num_dofs):
            row = psi[t * num_dofs + k]
            np.testing.assert_array_equal(row[k * num_basis:(k + 1) * num_basis], phi[t])
            other = np.delete(row, np.s_[k * num_basis:(k + 1) * num_basis])
            assert np.all(other == 0.0)
    # A weight vector reproduces y (T, D) flattened time-major.
    w = np.arange(num_dofs * num_basis, dtype=float)
    y = psi @ w
    expected = np.stack([phi @ w[k * num_basis:(k + 1) * num_basis] for k in range(num_dofs)], axis=1)
    np.testing.assert_allclose(y, expected.reshape(-1), rtol=1e-13)


@pytest.mark.parametrize("num_basis", [3, 8, 15])
def test_derivative_matches_central_differences(num_basis):
    phase = np.linspace(0.01, 0.99, 23)
    eps = 1e-6
    fd = (np.asarray(rbf_basis(phase + eps, num_basis)) - np.asarray(rbf_basis(phase - eps, num_basis))) / (2 * eps)
    analytic = np.asarray(rbf_basis_derivative(phase, num_basis))
    np.testing.assert_allclose(analytic, fd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(analytic.sum(axis=1), 0.0, atol=1e-10)


def test_velocity_design_divides_by_duration():
    phase = np.linspace(0, 1, 4)
    v1 = np.asarray(velocity_design_matrix(phase, 2, 5, duration=1.0))
    v2 = np.asarray(velocity_design_matrix(phase, 2, 5, duration=2.0))
    np.testing.assert_allclose(v2, v1 / 2.0)
    np.testing.assert_array_equal(np.asarray(block_basis(rbf_basis_derivative(phase, 5), 2)), v1)


def test_fewer_than_two_basis_functions_is_an_error():
    with pytest.raises(ValueError, match="num_basis"):
        rbf_basis([0.5], 1)
