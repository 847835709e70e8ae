from eqa.service import main
from services.stopper.service import StopperService

raise SystemExit(main(StopperService))
