"""Tables and samplers over the in-memory index of sampleable transitions.

Every sampleable transition gets a transition id (tid, in order of completion) and a row in flat
numpy columns (robot, reward, flags, next tid in its episode, priority...). A table is, per robot,
an append-only array of tids: "online" by default, any name a client inserts into ("demos"...),
and "interventions", which also holds every online/demo transition a human chose. A sample request
names tables with mixing ratios (RLPD's 50/50: {"online": 1, "demos": 1}); within a table the
sampler is uniform, a recency window (the newest W transitions) or prioritized (p^alpha, with
importance weights; priorities updated by the learner through UpdatePriorities).

A tid is a row of the columns: rows of evicted transitions stay (marked dead) until they are a quarter of
the rows, then compact() renumbers the live rows densely. Clients see public ids instead (Index.ids,
Batch.indices): ascending and never renumbered, mapped back to rows by binary search.

A row's LMDB key is not kept as a bytes object: it is its episode's prefix (stored once per episode, in a
slot) + its step index (a column), and each episode's rows are one int64 array. So the index costs ~100
bytes per transition in numpy/array columns instead of ~300 in Python objects (a key, a dict entry, ints).
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field

import numpy as np

from user.wire import split_rows

ONLINE = "online"
INTERVENTIONS = "interventions"
ALL = ""  # the union of this buffer's tables, each transition once (the legacy request); not attached ones
SAMPLERS = ("uniform", "recency", "prioritized")


class EmptyBufferError(RuntimeError):
    """Nothing sampleable (yet, or for the tables/robots asked for)."""


MAX_TREES = 64  # sum trees kept (one per table, robot and alpha asked for); more are rebuilt on demand
# priority**alpha is clipped to this in sum trees: float32's max ** 10 (the largest alpha) overflows float64, and a
# tree's total must stay finite for any number of leaves a table can hold
MAX_LEAF = 1e290


def _leaves(priorities: np.ndarray | float, alpha: float) -> np.ndarray:
    """Sum-tree leaves for priorities: priority**alpha in float64, at most MAX_LEAF."""
    with np.errstate(over="ignore"):
        return np.minimum(np.asarray(priorities, np.float64) ** alpha, MAX_LEAF)


class SumTree:
    """Priorities^alpha of one table's transitions (leaf i = position i of its tid column) in a binary sum tree.

    Appends and updates are O(log n) per leaf (vectorized over the leaves changed), a draw of k is
    O(k log n): no scan of the table per sample.
    """

    def __init__(self, values: np.ndarray) -> None:
        self.n = 0
        self.cap = 1
        self.tree = np.zeros(2, np.float64)
        self.extend(values)

    def _resize(self, need: int) -> None:
        cap = self.cap
        while cap < need:
            cap *= 2
        leaves = self.tree[self.cap : self.cap + self.n].copy()
        self.cap = cap
        self.tree = np.zeros(2 * cap, np.float64)
        self.tree[cap : cap + self.n] = leaves
        for lo in _levels(cap):  # every internal node once, bottom up
            self.tree[lo : 2 * lo] = self.tree[2 * lo : 4 * lo : 2] + self.tree[2 * lo + 1 : 4 * lo : 2]

    def extend(self, values: np.ndarray) -> None:
        need = self.n + len(values)
        if need > self.cap:
            self._resize(need)
        self.set(np.arange(self.n, need), values)
        self.n = need

    def set(self, positions: np.ndarray, values: np.ndarray) -> None:
        if len(positions) == 0:
            return
        node = positions + self.cap
        self.tree[node] = values
        node = np.unique(node // 2)
        while node[0] >= 1:
            self.tree[node] = self.tree[2 * node] + self.tree[2 * node + 1]
            if node[0] == 1:
                break
            node = np.unique(node // 2)

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def leaves(self, positions: np.ndarray) -> np.ndarray:
        return self.tree[positions + self.cap]

    def find(self, values: np.ndarray) -> np.ndarray:
        """Positions whose cumulative range holds each value in [0, total)."""
        node = np.ones(len(values), np.int64)
        v = values.astype(np.float64, copy=True)
        while node[0] < self.cap:
            left = self.tree[2 * node]
            right = v >= left
            v -= np.where(right, left, 0.0)
            node = 2 * node + right
        pos = np.minimum(node - self.cap, self.n - 1)
        # rounding can land on an empty leaf: take the nearest non-empty one before it
        bad = self.tree[pos + self.cap] <= 0
        if bad.any():
            nonzero = np.flatnonzero(self.tree[self.cap : self.cap + self.n] > 0)
            at = np.searchsorted(nonzero, pos[bad], side="right") - 1
            pos[bad] = nonzero[np.maximum(at, 0)]
        return pos


def _levels(cap: int) -> list[int]:
    """First node of each internal level, bottom up (cap/2, cap/4, ..., 1)."""
    out, lo = [], cap // 2
    while lo >= 1:
        out.append(lo)
        lo //= 2
    return out


class Grow:
    """A growable 1-D numpy column."""

    def __init__(self, dtype: type | np.dtype, fill: float | int = 0) -> None:
        self.a = np.full(1024, fill, dtype)
        self.n = 0
        self.fill = fill

    def append(self, value: float | int) -> None:
        if self.n == len(self.a):
            self.a = np.concatenate([self.a, np.full(len(self.a) // 2, self.fill, self.a.dtype)])
        self.a[self.n] = value
        self.n += 1

    def extend(self, values: np.ndarray) -> None:
        need = self.n + len(values)
        if need > len(self.a):
            size = max(need, len(self.a) + len(self.a) // 2)  # 1.5x: less slack than doubling
            self.a = np.concatenate([self.a, np.full(size - len(self.a), self.fill, self.a.dtype)])
        self.a[self.n : need] = values
        self.n = need

    def view(self) -> np.ndarray:
        return self.a[: self.n]

    def keep(self, mask: np.ndarray) -> None:
        kept = self.a[: self.n][mask]
        self.a[: len(kept)] = kept
        self.n = len(kept)

    def replace(self, values: np.ndarray) -> None:
        """Hold exactly `values` in a right-sized array, so capacity can shrink. Room for half more: the rows
        grow by at most a third of the live ones before the next compaction, so it is not regrown in between."""
        self.a = np.full(max(1024, len(values) + len(values) // 2), self.fill, self.a.dtype)
        self.a[: len(values)] = values
        self.n = len(values)


@dataclass(slots=True)
class Record:
    """One sampleable transition to index."""

    key: bytes
    robot: int  # Index.code(robot_id)
    table: str
    reward: float
    terminated: bool
    truncated: bool
    intervention: bool
    policy_version: int
    group: int = -1  # hot layout group, -1 unknown
    hot_row: int = -1


@dataclass
class Draw:
    """What a sample request asks the index for."""

    batch_size: int
    tables: dict[str, float] = field(default_factory=dict)  # name -> ratio; empty = all
    robot_ids: list[str] = field(default_factory=list)  # empty = all
    sampler: str = "uniform"
    window: int = 0  # recency: newest transitions per table
    alpha: float = 0.6  # prioritized
    beta: float = 0.4
    n_step: int = 1
    gamma: float = 0.99
    frame_stack: int = 1  # observations get an axis of the k newest frames (oldest first)
    encoded_frames: bool = False  # JPEG/PNG frames as kept (wire.EncodedFrames) where they share one encoding
    human_tables: tuple[str, ...] = ()  # rows drawn from these come flagged intervention (Drawn.human)
    table_robot_ids: dict[str, list[str]] = field(default_factory=dict)  # table -> its robots instead of robot_ids

    def robots_of(self, table: str) -> list[str]:
        """The robots `table`'s rows are drawn from (empty = all)."""
        return self.table_robot_ids.get(table, self.robot_ids)


@dataclass
class Drawn:
    tids: np.ndarray  # the transitions (observation, action)
    last: np.ndarray  # the transition whose next observation ends the n-step window
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    n_steps: np.ndarray
    weights: np.ndarray
    human: np.ndarray | None = None  # rows drawn from Draw.human_tables (None: none asked)


class Index:
    """Not thread-safe: the store calls it under its index lock."""

    def __init__(self) -> None:
        self.episode = Grow(np.int32)  # each row's episode slot (its key's prefix)
        self.step = Grow(np.int64)  # each row's step index (its key's last 8 bytes)
        self.robot = Grow(np.int32)
        self.group = Grow(np.int32, -1)  # hot layout group, -1 unknown
        self.hot_row = Grow(np.int64, -1)
        self.reward = Grow(np.float32)
        self.terminated = Grow(np.bool_)
        self.truncated = Grow(np.bool_)
        self.intervention = Grow(np.bool_)
        self.policy_version = Grow(np.int64)
        self.next_tid = Grow(np.int64, -1)
        self.prev_tid = Grow(np.int64, -1)
        self.alive = Grow(np.bool_)
        self.priority = Grow(np.float32, 1.0)
        self.ids = Grow(np.int64)  # each row's public id (Batch.indices): ascending, never reused or renumbered
        self.next_id = 0
        self.dead = 0  # rows of evicted transitions, until compact() drops them
        self.compact_min = 4096  # fewer dead rows are not worth a compaction
        self.max_priority = 1.0
        self._trees: dict[tuple[str, int, float], SumTree] = {}  # (table, robot code, alpha) -> tree
        self.robots: list[str] = []
        self.robot_code: dict[str, int] = {}
        self.tables: dict[str, dict[int, Grow]] = {}
        self.all: dict[int, Grow] = {}
        # episodes with indexed rows: slot -> key prefix and its rows (ascending); slots of evicted ones are reused
        self.prefixes: list[bytes] = []
        self.slot_of: dict[bytes, int] = {}
        self.episode_rows: list[array] = []
        self._free_slots: list[int] = []

    def __len__(self) -> int:
        return sum(g.n for g in self.all.values())

    @property
    def n_rows(self) -> int:
        """Rows, live and dead (a tid is < n_rows)."""
        return self.alive.n

    def code(self, robot_id: str) -> int:
        code = self.robot_code.get(robot_id)
        if code is None:
            code = self.robot_code[robot_id] = len(self.robots)
            self.robots.append(robot_id)
        return code

    # ------------------------------------------------------------------ keys

    def key(self, tid: int) -> bytes:
        """The LMDB key of a row (an attached buffer's keys keep their b"\0" + source mark)."""
        return self.prefixes[self.episode.a[tid]] + int(self.step.a[tid]).to_bytes(8, "big")

    def keys_of(self, tids: np.ndarray | list[int]) -> list[bytes]:
        tids = np.asarray(tids, np.int64)
        pre = self.prefixes
        return [
            pre[e] + t.to_bytes(8, "big")
            for e, t in zip(self.episode.a[tids].tolist(), self.step.a[tids].tolist(), strict=True)
        ]

    def _slot(self, prefix: bytes) -> int:
        slot = self.slot_of.get(prefix)
        if slot is None:
            if self._free_slots:
                slot = self._free_slots.pop()
                self.prefixes[slot] = prefix
                self.episode_rows[slot] = array("q")
            else:
                slot = len(self.prefixes)
                self.prefixes.append(prefix)
                self.episode_rows.append(array("q"))
            self.slot_of[prefix] = slot
        return slot

    def row_of(self, prefix: bytes, t: int) -> int:
        """The row of step t of an episode, -1 if it is not indexed. O(1) for the episode's newest row (the
        usual case), else O(episode length) in numpy."""
        slot = self.slot_of.get(prefix)
        if slot is None or t < 0:
            return -1
        rows = self.episode_rows[slot]
        if not rows:
            return -1
        if self.step.a[rows[-1]] == t:
            return rows[-1]
        mine = np.frombuffer(rows, np.int64).copy()  # a copy: a live view would stop the array from growing
        hit = mine[self.step.a[mine] == t]
        return int(hit[0]) if len(hit) else -1

    def _add_rows(self, prefixes: list[bytes], t: np.ndarray, first: int) -> None:
        """Episode slot and step columns of new rows first.. (prefixes usually repeat in runs), and each
        episode's row list."""
        n = len(prefixes)
        slots = np.empty(n, np.int32)
        i = 0
        while i < n:  # one slot lookup and one array extend per run of the same episode
            j = i + 1
            p = prefixes[i]
            while j < n and prefixes[j] == p:
                j += 1
            slot = self._slot(p)
            slots[i:j] = slot
            self.episode_rows[slot].extend(range(first + i, first + j))
            i = j
        self.episode.extend(slots)
        self.step.extend(t)

    def add_many(self, records: list[Record]) -> list[int]:
        """Index transitions in one go (column appends are vectorized); returns their tids."""
        first = self.n_rows
        tids = list(range(first, first + len(records)))
        prefixes = [r.key[:-8] for r in records]
        steps = np.fromiter((int.from_bytes(r.key[-8:], "big") for r in records), np.int64, len(records))
        self._add_rows(prefixes, steps, first)
        self.robot.extend(np.fromiter((r.robot for r in records), np.int32, len(records)))
        self.group.extend(np.fromiter((r.group for r in records), np.int32, len(records)))
        self.hot_row.extend(np.fromiter((r.hot_row for r in records), np.int64, len(records)))
        self.reward.extend(np.fromiter((r.reward for r in records), np.float32, len(records)))
        self.terminated.extend(np.fromiter((r.terminated for r in records), np.bool_, len(records)))
        self.truncated.extend(np.fromiter((r.truncated for r in records), np.bool_, len(records)))
        self.intervention.extend(np.fromiter((r.intervention for r in records), np.bool_, len(records)))
        self.policy_version.extend(np.fromiter((r.policy_version for r in records), np.int64, len(records)))
        self.next_tid.extend(np.full(len(records), -1, np.int64))
        self.prev_tid.extend(np.full(len(records), -1, np.int64))
        self.alive.extend(np.ones(len(records), np.bool_))
        self.priority.extend(np.full(len(records), self.max_priority, np.float32))
        self._new_ids(len(records))
        by_table: dict[tuple[str, int], list[int]] = {}
        self._link(prefixes, steps, first)
        for tid, r in zip(tids, records, strict=True):
            by_table.setdefault((r.table, r.robot), []).append(tid)
            if r.intervention and r.table != INTERVENTIONS:
                by_table.setdefault((INTERVENTIONS, r.robot), []).append(tid)
            if r.key[:1] != b"\0":  # attached buffers are sampled by their table name only
                by_table.setdefault((ALL, r.robot), []).append(tid)
        self._append_tables({k: np.asarray(v, np.int64) for k, v in by_table.items()})
        return tids

    def _link(self, prefixes: list[bytes], steps: np.ndarray, first: int) -> None:
        """Link new rows first.. to their episode neighbours for n-step returns, in any arrival order: within
        the batch by sorting (episode, step), to rows indexed before by one lookup per batch edge."""
        n = len(steps)
        tids = np.arange(first, first + n, dtype=np.int64)
        slots = self.episode.a[first : first + n]
        order = np.lexsort((steps, slots))
        s, t, tid = slots[order], steps[order], tids[order]
        adj = (s[1:] == s[:-1]) & (t[1:] == t[:-1] + 1)
        self.prev_tid.a[tid[1:][adj]] = tid[:-1][adj]
        self.next_tid.a[tid[:-1][adj]] = tid[1:][adj]
        has_prev = np.zeros(n, np.bool_)
        has_prev[1:] = adj
        has_next = np.zeros(n, np.bool_)
        has_next[:-1] = adj
        for i in np.flatnonzero(~has_prev & (t > 0)).tolist():
            row = self.row_of(prefixes[order[i]], int(t[i]) - 1)
            if row >= 0:
                self.next_tid.a[row] = tid[i]
                self.prev_tid.a[tid[i]] = row
        for i in np.flatnonzero(~has_next).tolist():
            row = self.row_of(prefixes[order[i]], int(t[i]) + 1)
            if row >= 0:
                self.next_tid.a[tid[i]] = row
                self.prev_tid.a[row] = tid[i]

    def _new_ids(self, n: int) -> None:
        self.ids.extend(np.arange(self.next_id, self.next_id + n, dtype=np.int64))
        self.next_id += n

    def rows_of(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of public ids, and which ids are still indexed (evicted or unknown ones are not)."""
        col = self.ids.view()
        if len(col) == 0:
            return np.zeros(len(ids), np.int64), np.zeros(len(ids), np.bool_)
        rows = np.minimum(np.searchsorted(col, ids), len(col) - 1)
        ok = col[rows] == ids
        ok[ok] = self.alive.a[rows[ok]]
        return rows, ok

    def _append_tables(self, by_table: dict[tuple[str, int], np.ndarray]) -> None:
        """New tids (ascending) onto their (table, robot) columns, and onto the sum trees built over them."""
        for (table, code), ids in by_table.items():
            grows = self.all if table == ALL else self.tables.setdefault(table, {})
            grow = grows.get(code)
            if grow is None:
                grow = grows[code] = Grow(np.int64)
            grow.extend(ids)
            for (t_name, t_code, alpha), tree in self._trees.items():
                if t_name == table and t_code == code:
                    tree.extend(np.full(len(ids), _leaves(self.max_priority, alpha)))

    def add_columns(
        self,
        keys: list[bytes],
        robot: np.ndarray,
        tables: list[str],
        reward: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        intervention: np.ndarray,
        policy_version: np.ndarray,
        group: np.ndarray,
        hot_row: np.ndarray,
    ) -> np.ndarray:
        """add_many for transitions that arrived in order (none has a successor indexed yet), as columns:
        a transition's predecessor is the one before it in the batch, else looked up once per episode."""
        n = len(keys)
        first = self.n_rows
        tids = np.arange(first, first + n, dtype=np.int64)
        prefixes = [k[:-8] for k in keys]
        t = np.fromiter((int.from_bytes(k[-8:], "big") for k in keys), np.int64, n)
        prev = np.full(n, -1, np.int64)
        if n > 1:
            adj = np.fromiter(map(bytes.__eq__, prefixes[1:], prefixes[:-1]), np.bool_, n - 1) & (t[1:] == t[:-1] + 1)
            prev[1:][adj] = tids[:-1][adj]
        for i in np.flatnonzero((prev < 0) & (t > 0)).tolist():  # before this batch's rows exist
            prev[i] = self.row_of(prefixes[i], int(t[i]) - 1)
        self._add_rows(prefixes, t, first)
        self.robot.extend(robot)
        self.group.extend(group)
        self.hot_row.extend(hot_row)
        self.reward.extend(reward)
        self.terminated.extend(terminated)
        self.truncated.extend(truncated)
        self.intervention.extend(intervention)
        self.policy_version.extend(policy_version)
        self.next_tid.extend(np.full(n, -1, np.int64))
        self.prev_tid.extend(np.full(n, -1, np.int64))
        self.alive.extend(np.ones(n, np.bool_))
        self.priority.extend(np.full(n, self.max_priority, np.float32))
        self._new_ids(n)
        has = prev >= 0
        self.prev_tid.a[tids[has]] = prev[has]
        self.next_tid.a[prev[has]] = tids[has]
        names = set(tables)
        table_of = np.asarray(tables) if len(names) > 1 else None
        by_table: dict[tuple[str, int], np.ndarray] = {}
        for code in np.unique(robot).tolist():
            mine = robot == code
            for name in names:
                m = mine if table_of is None else mine & (table_of == name)
                if m.any():
                    by_table[(name, code)] = tids[m]
            m = mine & intervention
            if table_of is not None:
                m &= table_of != INTERVENTIONS
            if m.any() and INTERVENTIONS not in names:
                by_table[(INTERVENTIONS, code)] = tids[m]
            elif m.any():
                by_table[(INTERVENTIONS, code)] = np.union1d(by_table.get((INTERVENTIONS, code), tids[:0]), tids[m])
            by_table[(ALL, code)] = tids[mine]
        self._append_tables(by_table)
        return tids

    def evict_episodes(self, prefixes: list[bytes]) -> None:
        """Every indexed row of these episodes leaves (rows stay, dead, until compact())."""
        parts = []
        for prefix in prefixes:
            slot = self.slot_of.pop(prefix, None)
            if slot is None:
                continue
            parts.append(np.frombuffer(self.episode_rows[slot], np.int64).copy())
            self.prefixes[slot] = b""
            self.episode_rows[slot] = array("q")
            self._free_slots.append(slot)
        if not parts:
            return
        dead = np.concatenate(parts)
        self.dead += int(self.alive.a[dead].sum())
        self.alive.a[dead] = False
        for grows in [*self.tables.values(), self.all]:
            for g in grows.values():
                g.keep(self.alive.a[g.view()])
        self._trees.clear()  # positions moved: rebuilt on the next prioritized draw

    def wants_compaction(self) -> bool:
        """Once evicted rows are a quarter of the rows (and many), compact(): rows stay <= 4/3 of the live ones,
        and a compaction (O(rows), ~60 ms for 600k) comes once per a third of the live count evicted."""
        return self.dead >= self.compact_min and 4 * self.dead > self.n_rows

    def compact(self) -> np.ndarray:
        """Drop evicted rows: live rows are renumbered densely in order (public ids stay); returns old row -> new
        row (-1 for dropped), for every other holder of rows to remap. O(rows), vectorized."""
        n = self.n_rows
        live = np.flatnonzero(self.alive.view())
        remap = np.full(n, -1, np.int64)
        remap[live] = np.arange(len(live), dtype=np.int64)
        for col in (self.episode, self.step, self.robot, self.group, self.hot_row, self.reward, self.terminated,
                    self.truncated, self.intervention, self.policy_version, self.alive, self.priority,
                    self.ids):  # fmt: skip
            col.replace(col.view()[live])
        for col in (self.next_tid, self.prev_tid):  # links to evicted rows become -1
            old = col.view()[live]
            col.replace(np.where(old >= 0, remap[np.maximum(old, 0)], -1))
        for slot, rows in enumerate(self.episode_rows):  # live episodes only hold live rows: renumbered in order
            if rows:
                self.episode_rows[slot] = array("q", remap[np.frombuffer(rows, np.int64)].tobytes())
        for grows in [*self.tables.values(), self.all]:
            for g in grows.values():
                g.replace(remap[g.view()])  # tables hold live rows only (evict dropped the rest)
        self._trees.clear()
        self.dead = 0
        return remap

    # ------------------------------------------------------------------ counts

    def count(self, table: str = ALL, robot_ids: list[str] | None = None) -> int:
        grows = self.all if table == ALL else self.tables.get(table, {})
        codes = self._codes(robot_ids)
        return sum(g.n for c, g in grows.items() if codes is None or c in codes)

    def _codes(self, robot_ids: list[str] | None) -> set[int] | None:
        if not robot_ids:
            return None
        return {self.robot_code[r] for r in robot_ids if r in self.robot_code}

    def candidates(self, table: str, robot_ids: list[str] | None, newest: int = 0) -> np.ndarray:
        """Tids of a table (for the robots asked); with `newest`, at most that many of each robot's newest."""
        grows = self.all if table == ALL else self.tables.get(table, {})
        codes = self._codes(robot_ids)
        parts = [
            g.view()[-newest:] if newest else g.view()
            for c, g in sorted(grows.items())
            if g.n and (codes is None or c in codes)
        ]
        if not parts:
            return np.empty(0, np.int64)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    # ------------------------------------------------------------------ draws

    def draw(self, req: Draw, rng: np.random.Generator) -> Drawn:
        one = {next(iter(req.tables), ALL): req.batch_size}
        shares = split_rows(req.batch_size, req.tables) if len(req.tables) > 1 else one
        tids, weights, human = [], [], []
        for table, k in shares.items():
            if k == 0:
                continue
            human.append(np.full(k, table in req.human_tables))
            robot_ids = req.robots_of(table)
            if req.sampler == "prioritized":
                if self.count(table, robot_ids) == 0:
                    raise _empty(table, robot_ids)
                t, w = self._draw_prioritized(table, k, req, rng, robot_ids)
            else:
                newest = req.window if req.sampler == "recency" else 0  # tids grow with arrival: newest are last
                cands = self.candidates(table, robot_ids, newest)
                if len(cands) == 0:
                    raise _empty(table, robot_ids)
                t, w = self._draw_one(cands, k, req, rng)
            tids.append(t)
            weights.append(w)
        tid = np.concatenate(tids) if len(tids) > 1 else tids[0]
        weight = np.concatenate(weights) if len(weights) > 1 else weights[0]
        drawn = self._n_step(tid, weight, req.n_step, req.gamma)
        if req.human_tables:
            # a row of the union is a human table's when that table holds it (a transition is in one table)
            drawn.human = self.held_by(tid, req.human_tables) if ALL in shares else np.concatenate(human)
        return drawn

    def held_by(self, tids: np.ndarray, tables: tuple[str, ...]) -> np.ndarray:
        """Which of `tids` one of `tables` holds: a binary search per robot of the batch in that robot's
        column (tids ascending), never a scan of a table."""
        out = np.zeros(len(tids), np.bool_)
        held = [self.tables[t] for t in tables if t in self.tables]
        if not held or not len(tids):
            return out
        robot = self.robot.a[tids]
        for code in np.unique(robot).tolist():
            sel = np.flatnonzero(robot == code)
            mine = tids[sel]
            for grows in held:
                grow = grows.get(code)
                if grow is None or not grow.n:
                    continue
                col = grow.view()
                pos = np.minimum(np.searchsorted(col, mine), grow.n - 1)
                out[sel] |= col[pos] == mine
        return out

    def _draw_one(
        self, cands: np.ndarray, k: int, req: Draw, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        if req.sampler == "recency" and 0 < req.window < len(cands):
            cands = np.partition(cands, len(cands) - req.window)[-req.window :]
        return cands[rng.integers(0, len(cands), size=k)], np.ones(k, np.float32)

    def _tree(self, table: str, code: int, alpha: float) -> SumTree:
        key = (table, code, alpha)
        tree = self._trees.get(key)
        if tree is None:
            if len(self._trees) >= MAX_TREES:
                self._trees.pop(next(iter(self._trees)))
            grows = self.all if table == ALL else self.tables.get(table, {})
            tree = self._trees[key] = SumTree(_leaves(self.priority.a[grows[code].view()], alpha))
        return tree

    def _draw_prioritized(
        self, table: str, k: int, req: Draw, rng: np.random.Generator, robot_ids: list[str]
    ) -> tuple[np.ndarray, np.ndarray]:
        """k draws proportional to priority^alpha over the table's robots asked for: O(k log n) in sum trees."""
        grows = self.all if table == ALL else self.tables.get(table, {})
        codes = self._codes(robot_ids)
        parts = [(c, g) for c, g in sorted(grows.items()) if g.n and (codes is None or c in codes)]
        trees = [self._tree(table, c, req.alpha) for c, _ in parts]
        n = sum(g.n for _, g in parts)
        totals = np.array([t.total for t in trees], np.float64)
        total = float(totals.sum())
        if not total > 0:  # every priority 0: uniform
            cands = np.concatenate([g.view() for _, g in parts])
            return cands[rng.integers(0, n, size=k)], np.ones(k, np.float32)
        u = rng.random(k) * total
        edges = np.cumsum(totals)
        which = np.minimum(np.searchsorted(edges, u, side="right"), len(trees) - 1)
        tids = np.empty(k, np.int64)
        p = np.empty(k, np.float64)
        for i, ((_, g), tree) in enumerate(zip(parts, trees, strict=True)):
            sel = which == i
            if not sel.any():
                continue
            pos = tree.find(u[sel] - (edges[i] - totals[i]))
            tids[sel] = g.view()[pos]
            p[sel] = tree.leaves(pos)
        # (n p / total)^-beta over its max, as (p / min p)^-beta: no underflow of p / total to 0 (an infinite weight)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            w = (p / p.min()) ** (-req.beta)
        return tids, np.where(np.isfinite(w), w, 1.0).astype(np.float32)

    def _n_step(self, tids: np.ndarray, weights: np.ndarray, n: int, gamma: float) -> Drawn:
        if n <= 1:
            ones = np.ones(len(tids), np.int32)
            return Drawn(
                tids, tids, self.reward.a[tids], self.terminated.a[tids], self.truncated.a[tids], ones, weights
            )
        reward = self.reward.a[tids].astype(np.float32)
        term = self.terminated.a[tids].copy()
        trunc = self.truncated.a[tids].copy()
        last = tids.copy()
        n_steps = np.ones(len(tids), np.int32)
        stop = term | trunc
        discount = np.float32(gamma)
        for _ in range(1, n):
            nxt = self.next_tid.a[last]
            ok = ~stop & (nxt >= 0)
            ok[ok] = self.alive.a[nxt[ok]]
            if not ok.any():
                break
            on = nxt[ok]
            reward[ok] += discount * self.reward.a[on]
            last[ok] = on
            n_steps[ok] += 1
            term[ok] = self.terminated.a[on]
            trunc[ok] = self.truncated.a[on]
            stop = ~ok | term | trunc
            discount *= np.float32(gamma)
        return Drawn(tids, last, reward, term, trunc, n_steps, weights)

    def back(self, tids: np.ndarray, steps: int) -> np.ndarray:
        """The transitions `steps` earlier in the same episode, stopping at the earliest one indexed."""
        cur = tids.copy()
        for _ in range(steps):
            prev = self.prev_tid.a[cur]
            ok = prev >= 0
            ok[ok] = self.alive.a[prev[ok]]
            cur = np.where(ok, prev, cur)
        return cur

    def update_priorities(self, ids: np.ndarray, priorities: np.ndarray) -> int:
        """Set priorities of live transitions by public id; returns how many were updated (evicted ones are
        skipped)."""
        tids, ok = self.rows_of(ids)
        self.priority.a[tids[ok]] = priorities[ok]
        if self._trees and ok.any():
            live, values = tids[ok], priorities[ok].astype(np.float64)
            for (table, code, alpha), tree in self._trees.items():
                grows = self.all if table == ALL else self.tables.get(table, {})
                col = grows[code].view()
                pos = np.minimum(np.searchsorted(col, live), len(col) - 1)  # columns hold tids in ascending order
                mine = col[pos] == live
                tree.set(pos[mine], _leaves(values[mine], alpha))
        if ok.any():
            self.max_priority = max(self.max_priority, float(priorities[ok].max()))
        return int(ok.sum())


def _empty(table: str, robot_ids: list[str]) -> EmptyBufferError:
    what = f"table {table!r}" if table else "the buffer"
    robots = f" for robots {_some(sorted(set(robot_ids)))}" if robot_ids else ""
    return EmptyBufferError(f"no sampleable transitions in {what}{robots} yet")


def _some(names: list[str], shown: int = 8) -> str:
    """The first few names and how many more: a request may name thousands."""
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return f"{names[:shown]}{more}"
