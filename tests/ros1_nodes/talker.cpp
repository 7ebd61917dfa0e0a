// roscpp talker: publishes COUNT std_msgs/String "msg I" on TOPIC once a subscriber is connected.
#include <ros/ros.h>
#include <std_msgs/String.h>
#include <cstdlib>
#include <string>

int main(int argc, char** argv) {
  ros::init(argc, argv, "roscpp_talker", ros::init_options::NoSigintHandler);
  if (argc < 3) return 2;
  std::string topic = argv[1];
  int count = std::atoi(argv[2]);
  ros::NodeHandle nh;
  ros::Publisher pub = nh.advertise<std_msgs::String>(topic, 1000);
  ros::WallTime deadline = ros::WallTime::now() + ros::WallDuration(20.0);
  while (pub.getNumSubscribers() < 1 && ros::WallTime::now() < deadline) {
    ros::WallDuration(0.02).sleep();
  }
  ros::WallDuration(0.2).sleep();
  for (int i = 0; i < count; ++i) {
    std_msgs::String m;
    m.data = "msg " + std::to_string(i);
    pub.publish(m);
  }
  ros::WallDuration(1.0).sleep();
  std::printf("SENT %d\n", count);
  std::fflush(stdout);
  ros::shutdown();
  return 0;
}
