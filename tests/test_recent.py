"""kernels.recent.Kept: the few most recently asked values by key, each made once while kept, from
several threads at once."""
import sys
import threading

from kernels.recent import Kept


def test_a_kept_value_is_not_made_again_and_the_least_recently_asked_goes_first():
    made = []

    def make(key):
        def value():
            made.append(key)
            return key * 10
        return value

    kept = Kept(2)
    assert [kept.get(k, make(k)) for k in (1, 2, 1, 3, 1, 2)] == [10, 20, 10, 30, 10, 20]
    # 1, 2 made; 1 asked again (now the most recent), 3 made drops 2 (the least recent), not 1;
    # 1 kept; 2 made again, dropping 3
    assert made == [1, 2, 3, 2]
    assert len(kept) == 2
    kept.clear()
    assert len(kept) == 0 and kept.get(1, make(1)) == 10 and made[-1] == 1


def test_threads_asking_at_once_each_get_the_one_value_made():
    """Two threads asking overlapping keys of a small Kept (a plan on the caller's thread, a judged
    column's patches laid beside): no error, each key's value made once while kept."""
    kept = Kept(4)
    made, errors = [], []

    def make(key):
        def value():
            made.append(key)
            return (key,)
        return value

    def ask(keys):
        try:
            for k in keys:
                assert kept.get(k, make(k)) == (k,)
        except Exception as error:          # noqa: BLE001: any failure of the other thread, reported
            errors.append(error)
    runs = [threading.Thread(target=ask, args=([k % 6 for k in range(start, start + 20000)],)) for start in (0, 3)]
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)         # the threads handed the GIL at nearly every step: a dict without
    try:                                # a lock fails here (KeyError, or its size changed while iterated)
        for run in runs:
            run.start()
        for run in runs:
            run.join()
    finally:
        sys.setswitchinterval(interval)
    assert errors == [] and len(kept) == 4 and set(made) == set(range(6))
