from eqa.service import main
from services.ros2_bridge.service import Ros2BridgeService

raise SystemExit(main(Ros2BridgeService))
