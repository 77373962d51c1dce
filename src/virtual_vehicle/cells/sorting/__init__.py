"""The Virtual Vehicle as a distributed cell program: parcels sorted to exits by local decisions only (paper
Section 1 and Figure 2: each parcel moves as if it rode its own vehicle, made of whichever cells are under it).

Units: SI (m/s for wheel speeds). Every rule below reads only the cell's own sensors, state and configuration and
what its neighbours said last tick (:mod:`virtual_vehicle.cells.network.programs` contract, checked by
:func:`~virtual_vehicle.cells.network.programs.check_program`).

- *Routing*: one hop-distance gradient per exit (distance vector; a cell on the array's edge counts
  ``1 + edge_cost`` hops, so parcels travel inside the array and meet the edge only at their exit). A parcel
  descends the gradient of its goal exit, so it finds its exit, and a detour around dead cells, without any cell
  knowing the map.
- *Virtual vehicle tracking*: at an entry cell a new parcel gets an id (the tick it arrived, so smaller ids are
  older vehicles) and the goal its label gives (a barcode reader at the entry: ``labels``); the cells of a new
  parcel settle on the smallest of the ids the entry cells made. A cell that starts seeing a parcel adopts the
  record (id, goal) of a neighbour whose vehicle is moving into it (else the smallest id heard); elsewhere a cell
  never changes vehicle while it sees one, but for a cell that sees only an edge (its centre uncovered) of a
  vehicle no neighbour carries: that parcel has gone (seen under sentence loss at the entry, where the next parcel
  arrives at once), and the edge is the vehicle's a neighbour carries, which it takes. Nor does a cell that sees
  only an edge keep a vehicle that no neighbour across a side it sees covered carries (config ``sides``: the sensor
  at the point it shares with that neighbour, lit, so the body covers the neighbour too) while such a neighbour
  carries another: it takes that one's (stress floor 140: two edge cells, each hearing the other, kept a gone
  vehicle's id under the due parcel that waited on them). Cells under one vehicle agree on its
  direction: every cell proposes
  (its distance to the goal, the port toward its closest neighbour); the smallest proposal (the front cell's)
  spreads through the vehicle within ``reach`` hops (hop-limited, so what a departed cell said is soon forgotten),
  the current direction preferred on a tie so the vehicle does not dither (a cell that has just come under the
  vehicle prefers the vehicle's, as its neighbours' keys say: it has none of its own yet).
- *Traffic*: a vehicle moves only along cells it holds. Each front cell (whose neighbour ahead is not under the
  same vehicle) asks that neighbour; an empty cell grants itself to the asking vehicle (the oldest when several
  ask, every tick: the older parcel goes first at a merge, and a younger one yields even a cell it held, so two
  vehicles never wait for each other) and passes the request on, ``gap + 1`` cells deep (``gap + 1 + lead`` on a
  link slow enough that a vehicle would travel more than a cell while its run of held cells is told back:
  :func:`~.rules.lead_cells`; the vehicle still moves on a run of ``gap``, the rest is slack). A held cell reports back
  how many held cells run ahead of it (none from a held cell with a parked vehicle on a side neighbour: a body
  reaches past the cell centres it covers, so one cell row beside a parked parcel is no room to pass); a vehicle
  moves when the run ahead of every front cell is at least ``gap`` long (or leads off the array at its exit), else
  all its cells stop. A stop spreads through the vehicle from the
  cell ahead or beside, never from behind nor back to the cell it came from (the stop word names the port), so it
  runs along no loop; but once the cell that said it says go, its last stop still arrives along the longer ways
  through the vehicle's cells, a hop later for each hop longer, so a cleared stop is gone from a vehicle two or more
  cells wide only when those ways are longer than ``reach``: ``reach`` exchanges at most (a parked vehicle's every
  cell says stop).
  Parcels therefore keep ``gap`` free cells between them and do not collide. Two
  vehicles that meet head on would each hold what the other needs; a front cell that sees the cell ahead held for
  an older vehicle that asked from the far side (the held cell tells through which port it was asked), or carrying
  an older vehicle coming this way, makes its vehicle back off for as long as ``gap + 1`` cells take (straight
  back, or aside when that side is closed). A hold
  lasts ``max_age`` ticks after the last request that renewed it (one tick on ideal rounds), so on a network that
  delivers a sentence only every few ticks the chain of holds ahead of a vehicle does not fall apart between them.
- *Giving way* (liveness): the order every cell decides locally is the vehicle id, the tick the vehicle was made
  (smaller is older), within three classes: a vehicle giving way, then one due or carrying no sequence number, then
  a late one (its number not yet due; its requests are marked ``LATE`` in ``rdep``). A standing vehicle, parked or
  not, one of whose cells hears a request from a vehicle before it in that order (one giving way, or an older one
  that is not late), or from any vehicle while its own sequence number is not due, gives way for
  as long as a back-off takes: away from the asker, or through the first open side beside that way when it is closed
  (a one-way arrow, the edge, a hole). A parked vehicle giving way is not parked for that time: it leaves the bay,
  and then heads for a free one again (stress floors 59 and 96: parked on the due one's only way, it and the due
  one waited on each other for ever). A cell asked by several gives way to the first in the order holds go by
  (below), and a back-off from a younger asker proposes a larger distance than one from an older asker, so that a
  late vehicle squeezed between the due one and a younger late one moves out of the due one's way, not into its
  holds (stress floors 104 and 106 stood so for ever). A vehicle giving way (a cell of it within ``reach`` backs
  off: its proposal has distance 0, 1 from a younger asker, below every other) marks its requests (``rdep``'s high
  bit), and a cell is held for a marked asker before any other (then one due or carrying no number, then a late
  one, the oldest first in each): the cells it gives way into are not kept from it by the holds of the older
  vehicle it makes room for, nor are the due one's by the holds of a late one, whose number waits on it. A
  vehicle asked that cannot give way (every side but the asker's closed) asks the asker back, marked, and the
  asker gives way to it.
  Why no cycle of holds survives: a vehicle waits on another whose cell, carried or held, is the first not its own
  within ``gap + 1`` cells ahead of a front cell, and a late vehicle waits on the due one (:mod:`.holds`). Take a
  cycle none of whose members gives way. An empty cell is held for the first asker in the order above, re-decided
  every tick, so a wait on a held cell is a wait on a vehicle before the waiting one in that order, and so is a
  late one's wait on the due one; the order cannot fall all the way around a cycle, so some member X waits on a
  Y after it, and then on a cell Y *carries*. X's request reaches that cell (the cells before it are held for X
  and pass the request on ``gap + 1`` deep), so Y hears an asker before it (or Y is late, parked or not, and gives
  way to any asker) and gives way: a cycle without a member giving way does not last a tick. A member giving way
  moves unless the way it gives way into is carried: by a standing vehicle, which its marked request asks and
  which gives way in turn, or by a moving one, which leaves it; or it is boxed in, and then X gives way to it.
  Where the argument has gaps (what the stress test measures): a chain of vehicles giving way can end at two that
  are each boxed in but for the other (each asks the other back: both stand); a back-off lasts ``gap + 1`` cells, and
  nothing here proves that two vehicles do not meet again the same way after it (a livelock, not a cycle of holds);
  and the cells' words travel a hop a tick, so a cycle can stand for the ticks its requests take to arrive.
- *Exits*: a cell of the goal's exit lane drives the vehicle out through the lane's open side once the vehicle lies
  within the lane (no cell beside it, across the way out, is under the vehicle without belonging to the lane);
  until then such cells move the vehicle sideways into the lane; on a slow link (``lead`` above 0) no further: a
  front cell of the lane facing out of it across a lane side stops the vehicle there (unless it gives way), so
  that where the cells agree on the turn out late the body does not run past the lane and come back. Nowhere
  else may a vehicle move over the edge: a front cell with no neighbour ahead stops it.
- *Dead cells* (silent neighbours on the ports config ``inner`` names: a neighbour installed, not on the edge): a
  dead cell carries weight and holds its wheels still, so it brakes a parcel over it while the live cells under
  the parcel drive it. A side on which a carrying cell has
  no neighbour is closed to the whole vehicle (and a front cell facing it stops the vehicle), except where the
  neighbour is dead and a cell of the same vehicle beside this one (across that side) has a live cell there: the
  vehicle then passes over the dead cell, carried by its live cells, where closing the side would leave a parcel
  wider than the gaps between dead cells shuffling in front of them. Nor does a vehicle step where that brings a
  second dead cell under it in line with one it covers: a carrying cell whose dead neighbour on a side lies under
  the body (its sensor toward it lit, and the neighbour across from it not saying the body covers its centre)
  closes the way ahead when the live cell there says a dead neighbour on the same side (a parcel of four cells,
  two dead, stands for good: held wheels brake with up to mu_static N at rest). Each cell says its dead ports in
  its ``ack`` word (bits 12 up) and, next to a dead cell, whether the body covers its centre (``blk``'s bit 30,
  above the side fields). Next to a dead cell a cell takes the smaller id
  of a neighbour that says the same goal, so that a dead cell that cuts a parcel's cells apart does not leave it
  carrying two ids that pull it two ways.
- *One-way cells* (config ``forbid``: the port a parcel on the cell may not move toward): gradients are not
  followed against the arrow, and a side against an arrow under any carrying cell is closed to the whole vehicle.
  Aisles drawn one-way cannot have two parcels meet head on (a parcel does not back off against an arrow: it steps
  aside, where it can).
- *Sequencing* (parcels whose label carries a sequence number, :func:`encode_goal`): the number due next spreads
  through the array as the highest heard (word ``nxt``); the exit cell that lets a sequenced parcel out raises it
  to that parcel's number plus one. A parcel whose number is not yet due follows gradient :data:`PARK` to a parking
  cell (config ``park``) whose centre no parcel covers, and parks once a cell carrying it is one: it stops, asks
  for no cells, and it and the cells beside it tell their neighbours there is no way through (so others route
  around it). When its number is due it heads for its exit. Parcels therefore leave in sequence, as long as there
  are enough parking cells for those that arrive early.

- *Square and hexagonal lattices*: a cell has P ports, four (east, north, west, south) or six (every 60 degrees
  counter-clockwise from its wheel-0 drive direction), all cells of the array alike. The rules speak of ports only
  through a few helpers (:mod:`.rules`): the port *ahead* is the vehicle's direction; *behind* is the port
  straight across from it (:func:`~.rules.opposite`, P/2 ports on: a stop is not taken from there, a request is
  passed on straight through it, a vehicle backs off through it); every other port is *beside* (two on a square
  cell; on a hexagonal one the two 60 degrees off ahead and the two 120 degrees off). A *side* is one port:
  it is closed to a vehicle when any cell carrying it has no live neighbour there, so a vehicle sidesteps through
  any open port, six on a hexagonal cell, toward the neighbour nearest its exit. The exit gradients are the same
  distance vectors over all P neighbours (a hop is one neighbour, a pitch away on either lattice). An exit lane's
  sides are the ports next to its way out (:func:`~.rules.left_of`, :func:`~.rules.right_of`: 90 degrees off it
  on a square cell, 60 on a hexagonal one); a lane cell that sees the vehicle beside it outside the lane moves it
  through that side mirrored across the way out (:func:`~.rules.into_lane`: straight sideways on a square cell;
  on a hexagonal one sideways and on toward the edge, there being no port straight sideways); next to a dead cell
  only while that side is open to the vehicle (the gradient moves the vehicle along until it opens). The wheels move a
  parcel out through port q at the vehicle's speed (:func:`~.rules.heading`): a square cell drives one of its
  two wheels, a hexagonal cell's omni wheels the velocity at ``60 q`` degrees in its frame. Words that pack a hop
  count with a port or one per port (``stop``, ``blk``) give it six bits on a square cell and five on a
  hexagonal one (:func:`~.rules.hop_bits`), so ``reach`` is at most 30 there. On a hexagonal lattice an exit lane
  leaves through an edge where the rows end (the top and bottom edges zig-zag: two ports lead off them as much),
  one-way cells are not drawn and the central sorter does not run; each is refused, naming it.

The policy is written once, compiled (:mod:`.policy`, one function per phase); :class:`Sorter` runs it.
:class:`CentralSorter` (:mod:`.central`) is the central counterpart for comparison; what both apply (the goal
encoding, when a parcel is due, vehicle ids, the gradients' hop cost, the wheel command, the back-off) is in
:mod:`.rules`.
"""

from virtual_vehicle.cells.network.programs import UNREACHABLE
from virtual_vehicle.cells.sorting.central import CentralSorter
from virtual_vehicle.cells.sorting.rules import MAX_EXITS, PARK, decode_goal, encode_goal
from virtual_vehicle.cells.sorting.sorter import Sorter

__all__ = ["MAX_EXITS", "PARK", "UNREACHABLE", "CentralSorter", "Sorter", "decode_goal", "encode_goal"]
