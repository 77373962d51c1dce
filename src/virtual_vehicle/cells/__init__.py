"""What runs on and in the cells: hardware (sensors, motors), field design (wheel speeds for a twist or a wrench), the
neighbour-only network (sentences, topology, delivery models) and the cell programs.
"""
