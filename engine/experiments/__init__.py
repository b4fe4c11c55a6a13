"""The paper's studies and the demo, built on the library; each is a module to run:

* :mod:`.demo` -- a bundled room end to end (``python3 build.py demo``);
* :mod:`.casestudy` -- the paper's section IV: database, localization, deployment loop;
* :mod:`.deployment` -- a robot in a (perturbed) real room localizing against the
  twin's database, step by step;
* :mod:`.lab_calibration` -- the lab calibrated from a lap recorded in its "real" room;
* :mod:`.sensing_demo` -- radar tracking, range-Doppler maps, the ISAC trade-off.

Nothing is imported here: each study pulls in what it needs when it runs.
"""

__all__: list[str] = []
