from eqa.service import main
from services.planner.service import PlannerService

raise SystemExit(main(PlannerService))
