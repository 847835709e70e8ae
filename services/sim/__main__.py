from eqa.service import main
from services.sim.service import SimService

raise SystemExit(main(SimService))
