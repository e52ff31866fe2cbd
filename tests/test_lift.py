import torch

from matspray.lift import weighted_median


def test_weighted_median_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    n_groups = 20
    group_ids = torch.randint(0, n_groups, (500,), generator=g)
    values = torch.randint(0, 256, (500,), generator=g).float() / 255  # PNG-like values
    counts = torch.randint(1, 5, (500,), generator=g)
    medians, has = weighted_median(group_ids, values, counts, n_groups + 2)
    assert not has[n_groups:].any() and (medians[n_groups:] == 0).all()
    for group in range(n_groups):
        members = group_ids == group
        expanded = values[members].repeat_interleave(counts[members])  # each sample as often as it hit
        assert has[group]
        assert medians[group] == torch.sort(expanded).values[(len(expanded) - 1) // 2]  # torch.median's lower median


def test_weighted_median_single_and_tied_values():
    medians, has = weighted_median(torch.tensor([0, 0, 0, 1]), torch.tensor([0.2, 0.9, 0.9, 0.4]), torch.tensor([1, 1, 1, 7]), 2)
    assert medians.tolist() == [0.8999999761581421, 0.4000000059604645] and has.all()
