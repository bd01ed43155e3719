"""Write a float .ply as .spz with gsply (which stores the .ply's axes unconverted).
Usage: python make-spz-gsply.py in.ply out.spz VERSION"""
import sys

import gsply

src, dst, version = sys.argv[1], sys.argv[2], int(sys.argv[3])
gsply.write_spz(dst, gsply.plyread(src), version=version)
print(dst, "written by gsply", gsply.__version__)
