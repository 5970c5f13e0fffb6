"""cell.core.recent.Recent: the few most recently asked values by key, each made once while kept."""
from cell.core.recent import Recent


def test_a_kept_value_is_not_made_again_and_the_least_recently_asked_goes_first():
    made = []

    def make(key):
        def value():
            made.append(key)
            return key * 10
        return value

    kept = Recent(2)
    assert [kept.get(k, make(k)) for k in (1, 2, 1, 3, 1, 2)] == [10, 20, 10, 30, 10, 20]
    # 1, 2 made; 1 asked again (now the most recent), 3 made drops 2 (the least recent), not 1;
    # 1 kept; 2 made again, dropping 3
    assert made == [1, 2, 3, 2]
    assert len(kept) == 2
    kept.clear()
    assert len(kept) == 0 and kept.get(1, make(1)) == 10 and made[-1] == 1
